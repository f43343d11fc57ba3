"""Typed errors of lidar_obstacles.

Library code raises these and never prints or exits; the nodes turn them into a throttled
warning plus a diagnostics count, the CLI into one line on stderr and exit status 2.
"""
from __future__ import annotations


class LidarObstaclesError(Exception):
    """Base of every error this package raises on bad input."""


class CloudFormatError(LidarObstaclesError):
    """A PointCloud2 (or point array) whose layout or content cannot be used."""


class ConfigError(LidarObstaclesError):
    """A parameter that is unknown, of the wrong type or out of its range."""


class BagError(LidarObstaclesError):
    """A bag that is missing, empty, corrupt or has no usable topic."""


class LasError(LidarObstaclesError):
    """A LAS/LAZ file that cannot be read or has no points."""


def reason_key(message: str) -> str:
    """The kind of an error, for counting rejected clouds by reason: its message up to the
    first detail (": ..." or " (...)"), at most 80 characters. "cloud has no 'z' field
    (fields: x, y)" counts as "cloud has no 'z' field"."""
    cut = min((i for i in (message.find(": "), message.find(" (")) if i > 0),
              default=len(message))
    return message[:cut][:80]
