"""Rolling local ground model kept between messages.

A UAV scan message is a thin strip; filtering it alone judges the ground at its edges
from one side only. The model keeps, per `context.cell` cell, the lowest ground height of
recent messages, so a new strip is filtered with the ground around it. Bounded: cells
further than `context.radius` from the newest message or older than `context.seconds` are
dropped, so memory stays flat however long the flight.
"""
from __future__ import annotations

import numpy as np

from lidar_obstacles.config import ContextConfig


class GroundContext:
    """Sparse grid of ground heights: cell keys (int64 pairs), heights, stamps."""

    def __init__(self, cfg: ContextConfig) -> None:
        self.cfg = cfg
        self._ij = np.zeros((0, 2), np.int64)
        self._z = np.zeros(0, np.float64)
        self._t = np.zeros(0, np.float64)

    def __len__(self) -> int:
        return len(self._z)

    def points_near(self, lo: np.ndarray, hi: np.ndarray, stamp: float) -> np.ndarray | None:
        """(M, 3) float64 ground points (cell centres, stored height) within `radius` of
        the box lo..hi (xy, metres) and no older than `seconds`; None when empty."""
        if len(self._z) == 0 or self.cfg.radius <= 0:
            return None
        c = self.cfg.cell
        xy = (self._ij + 0.5) * c
        r = self.cfg.radius
        keep = ((xy[:, 0] >= lo[0] - r) & (xy[:, 0] <= hi[0] + r)
                & (xy[:, 1] >= lo[1] - r) & (xy[:, 1] <= hi[1] + r)
                & (self._t >= stamp - self.cfg.seconds))
        if not keep.any():
            return None
        return np.column_stack([xy[keep], self._z[keep]])

    def update(self, ground_xyz: np.ndarray, stamp: float,
               cloud_xy: np.ndarray | None = None) -> None:
        """Merge a message's ground (N, 3) and forget what is too far or too old.

        cloud_xy: (M, 2) all the message's points; when given, only ground at least
        `context.margin` inside the message's footprint is kept. At a strip's edge the
        filter saw the terrain from one side only, and a wrong label there, remembered,
        would be carried into every later strip."""
        if self.cfg.radius <= 0 or self.cfg.seconds <= 0:
            return
        c = self.cfg.cell
        if cloud_xy is not None and self.cfg.margin > 0 and len(ground_xyz):
            ground_xyz = ground_xyz[_inside(ground_xyz[:, :2], cloud_xy, c, self.cfg.margin)]
        if len(ground_xyz):
            ij = np.floor(ground_xyz[:, :2] / c).astype(np.int64)
            ij_all = np.concatenate([self._ij, ij])
            z_all = np.concatenate([self._z, ground_xyz[:, 2]])
            t_all = np.concatenate([self._t, np.full(len(ij), float(stamp))])
            # Newest stamp wins per cell; within a stamp the lowest height (ground is low).
            order = np.lexsort((z_all, -t_all, ij_all[:, 1], ij_all[:, 0]))
            ij_s = ij_all[order]
            first = np.ones(len(order), bool)
            first[1:] = np.any(ij_s[1:] != ij_s[:-1], axis=1)
            pick = order[first]
            self._ij, self._z, self._t = ij_all[pick], z_all[pick], t_all[pick]
            centre = ground_xyz[:, :2].mean(axis=0)
            half = np.ptp(ground_xyz[:, :2], axis=0) / 2 + self.cfg.radius
            xy = (self._ij + 0.5) * c
            near = np.all(np.abs(xy - centre) <= half, axis=1)
        else:
            near = np.ones(len(self._z), bool)
        fresh = self._t >= stamp - self.cfg.seconds
        keep = near & fresh
        self._ij, self._z, self._t = self._ij[keep], self._z[keep], self._t[keep]


def _inside(xy: np.ndarray, cloud_xy: np.ndarray, cell: float, margin: float) -> np.ndarray:
    """(N,) bool: points xy (N, 2) lying at least `margin` metres inside the footprint of
    cloud_xy (M, 2), the footprint being its occupied `cell` cells (holes count as
    outside, as they are in the data)."""
    from scipy import ndimage

    lo = cloud_xy.min(axis=0) - cell
    ij = np.floor((cloud_xy - lo) / cell).astype(np.int64)
    occupied = np.zeros((int(ij[:, 1].max()) + 2, int(ij[:, 0].max()) + 2), bool)
    occupied[ij[:, 1], ij[:, 0]] = True
    depth = ndimage.distance_transform_edt(occupied) * cell
    pij = np.clip(np.floor((xy - lo) / cell).astype(np.int64), 0,
                  np.array(occupied.shape[::-1]) - 1)
    return depth[pij[:, 1], pij[:, 0]] >= margin
