"""Typed errors of lidar_obstacles.

Library code raises these and never prints or exits; the nodes turn them into a throttled
warning plus a diagnostics count, the CLI into one line on stderr and exit status 2.
"""
from __future__ import annotations

import re


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


class OutputError(LidarObstaclesError):
    """An output path that holds something else (a folder, a file of another kind), which
    is the user's data and not replaced."""


SKIP_MALFORMED_HINT = "--skip-malformed skips such clouds and counts them"


def malformed_cloud(index: int, topic: str, stamp_ns: int, exc: CloudFormatError
                    ) -> CloudFormatError:
    """The error that stops an offline command at a cloud of a bag it cannot use (malformed,
    or over `input.max_points`): which cloud (1-based `index` on `topic`, its header
    stamp), why, and how to go on without it. The nodes drop such a cloud and count it;
    offline, bad input stops the command unless the user asked to skip it (the contract:
    bad input of any kind, a malformed cloud included, ends with one line naming it and a
    non-zero status)."""
    return CloudFormatError(f"cloud {index} on {topic} (stamp {stamp_ns // 10**9}."
                            f"{stamp_ns % 10**9:09d} s): {exc} ({SKIP_MALFORMED_HINT})")


# A number in an error message: 8, -5, 25,000,000, 1.5, 1e+15 (not the 32 of FLOAT32).
_NUMBER = re.compile(r"(?<!\w)\d+(?:[.,]\d+)*(?:[eE][-+]?\d+)?")
_DETAIL = re.compile(r" ?\([^()]*\)")  # an innermost (perhaps empty) parenthesis, its space


# Reasons counted apart, at most; the rest count together (a flood of clouds whose
# field names change each time made one key per cloud: 19 994 after 20 000).
MAX_REASON_KEYS = 32
OTHER_REASONS = "other reasons"


def count_reason(reasons: dict[str, int], message: str) -> str:
    """Count a rejected cloud in `reasons` under the key of its error `message`
    (:func:`reason_key`), or under OTHER_REASONS once MAX_REASON_KEYS kinds are counted.
    Returns the key."""
    key = reason_key(message)
    if key not in reasons and len(reasons) >= MAX_REASON_KEYS:
        key = OTHER_REASONS
    reasons[key] = reasons.get(key, 0) + 1
    return key


def reason_key(message: str) -> str:
    """The kind of an error, for counting rejected clouds by reason: its message without
    its details (a parenthesis, anything after ": "), every number as N, at most 80
    characters. The keys are the /diagnostics keys `dropped: <reason>` and replay's JSON
    keys, so they must not grow with the clouds: "cloud has 4407 points, more than
    input.max_points=100" counts as "cloud has N points, more than input.max_points=N",
    "cloud has no 'z' field (fields: x, y)" as "cloud has no 'z' field"."""
    kind, found = message, 1
    while found:  # nested ones from the inside out
        kind, found = _DETAIL.subn("", kind)
    return _NUMBER.sub("N", kind.split(": ", 1)[0])[:80]
