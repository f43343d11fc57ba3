"""Obstacle grouping and classification (ASPRS codes), and the clearance grid.

Per point, from local PCA of the k nearest neighbours (eigenvalues l1 >= l2 >= l3):
linearity (l1 - l2) / l1, planarity (l2 - l3) / l1 and the direction of the main axis.

1. Noise (7): points with too few neighbours within `noise_radius`, or far below ground.
2. Wires (14): linear, near-horizontal points high above ground with empty space below
   them, kept only when they join into long runs (a wire spans tens of metres).
3. The other points above `min_height` are grouped into objects: connected components of a
   voxel grid of edge `cluster_distance` (26-neighbourhood).
4. Per object: towers (15) are tall, slender and carry wires (wire runs end next to
   them, no lower than their top);
   buildings (6) are mostly planar and their main plane, found with the RANSAC robust
   eigenvalue fit, is large; poles and other slender things are unclassified (1); the rest
   is vegetation by height above ground (3 < 0.5 m <= 4 <= 2 m < 5).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lidar_obstacles.config import ClearanceConfig, ObstaclesConfig
from lidar_obstacles.core.classes import (
    BUILDING,
    GROUND,
    NOISE,
    TOWER,
    UNCLASSIFIED,
    WIRE,
    vegetation_class,
)
from lidar_obstacles.core.ransac import ransac_plane

NEIGHBOURS = 10  # k of the PCA neighbourhoods
BELOW_GROUND_NOISE = 1.5  # m: points this far below the ground surface are noise
WIRE_GAP = 2.5  # m: a wire point has no other point from this far below it up to 0.5 m
WIRE_MIN_RUN = 10.0  # m: wire candidates joined into shorter runs are not wires
TOWER_WIRE_GAP = 3.0  # m: a tower has wire points this close to it
TOWER_BASE_MAX = 15.0  # m: widest tower base whose ground points are relabelled
TOWER_RADIUS = 0.25  # towers: points within this share of the height from the top's axis
SLENDER = 0.8  # towers/poles: horizontal extent below this share of their height
PLANAR_SHARE = 0.4  # buildings: share of the object's points on its main RANSAC plane


@dataclass(frozen=True)
class ObstacleObject:
    """One obstacle: ASPRS class, point count, box (m), height and clearance above ground."""

    id: int
    cls: int
    n_points: int
    min_xyz: np.ndarray
    max_xyz: np.ndarray
    centroid: np.ndarray
    height_above_ground: float  # highest point above ground, m
    clearance: float  # lowest point above ground (a wire's sag clearance), m


@dataclass(frozen=True)
class ObstacleClasses:
    """classes: (N,) uint8 ASPRS; object_id: (N,) int32 (-1 outside objects)."""

    classes: np.ndarray
    object_id: np.ndarray
    objects: tuple[ObstacleObject, ...]
    timings: dict[str, float] = field(default_factory=dict)


def pca_features(xyz: np.ndarray, k: int = NEIGHBOURS) -> tuple[np.ndarray, ...]:
    """Per point: linearity, planarity, |z of the main axis|, |z of the normal|. (M,) each."""
    m = len(xyz)
    if m < 3:
        z = np.zeros(m)
        return z, z, z, np.ones(m)
    k = min(k, m)
    _, nn = cKDTree(xyz).query(xyz, k=k, workers=-1)
    nb = xyz[nn]
    nb -= nb.mean(axis=1, keepdims=True)
    # The six distinct covariance terms directly: ~10 x faster than an einsum over (m,k,3,3).
    cov = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = (nb[:, :, a] * nb[:, :, b]).mean(axis=1)
    w, v = np.linalg.eigh(cov)  # ascending
    l1 = np.maximum(w[:, 2], 1e-12)
    linearity = (w[:, 2] - w[:, 1]) / l1
    planarity = (w[:, 1] - w[:, 0]) / l1
    return linearity, planarity, np.abs(v[:, 2, 2]), np.abs(v[:, 2, 0])


def voxel_components(xyz: np.ndarray, size: float) -> np.ndarray:
    """(M,) int labels: connected components of occupied voxels (26-neighbourhood)."""
    m = len(xyz)
    if m == 0:
        return np.zeros(0, np.int64)
    ijk = np.floor((xyz - xyz.min(axis=0)) / size).astype(np.int64) + 1
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    vox, inv = np.unique(key, return_inverse=True)
    rows, cols = [], []
    offsets = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                        if (a, b, c) > (0, 0, 0)])
    vijk = np.column_stack([vox // (dims[1] * dims[2]), (vox // dims[2]) % dims[1],
                            vox % dims[2]])
    for off in offsets:
        nkey = ((vijk[:, 0] + off[0]) * dims[1] + vijk[:, 1] + off[1]) * dims[2] + vijk[:, 2] + off[2]
        pos = np.searchsorted(vox, nkey)
        pos = np.minimum(pos, len(vox) - 1)
        hit = vox[pos] == nkey
        rows.append(np.flatnonzero(hit))
        cols.append(pos[hit])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(len(vox), len(vox)))
    _, labels = connected_components(graph, directed=False)
    return labels[inv]


def _empty_below(xyz: np.ndarray, cand: np.ndarray, others: np.ndarray) -> np.ndarray:
    """For candidate points, True when no point of `others` lies within 1 m horizontally
    and between WIRE_GAP and 0.5 m below them."""
    ok = np.ones(len(cand), bool)
    if len(others) == 0 or len(cand) == 0:
        return ok
    tree = cKDTree(xyz[others, :2])
    lists = tree.query_ball_point(xyz[cand, :2], r=1.0, workers=-1)
    lens = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if lens.sum() == 0:
        return ok
    owner = np.repeat(np.arange(len(cand)), lens)
    idx = others[np.concatenate([np.asarray(x, np.int64) for x in lists if len(x)])]
    dz = xyz[cand[owner], 2] - xyz[idx, 2]
    blocked = (dz > 0.5) & (dz < WIRE_GAP)
    ok[np.unique(owner[blocked])] = False
    return ok


def classify_obstacles(xyz: np.ndarray, ground: np.ndarray, height_above_ground: np.ndarray, *,
                       cfg: ObstaclesConfig, intensity: np.ndarray | None = None,
                       return_number: np.ndarray | None = None,
                       number_of_returns: np.ndarray | None = None,
                       rng: np.random.Generator | None = None) -> ObstacleClasses:
    """Classes of every point of (N, 3) float64 xyz (m) given the ground mask (N,) bool and
    the height above ground (N,) float32 m (NaN: unknown, taken as 0)."""
    t0 = time.perf_counter()
    rng = rng or np.random.default_rng(0)
    n = len(xyz)
    classes = np.full(n, GROUND, np.uint8)
    object_id = np.full(n, -1, np.int32)
    if n == 0:
        return ObstacleClasses(classes, object_id, (), {"total": 0.0})
    hag = np.nan_to_num(np.asarray(height_above_ground, np.float64), nan=0.0)
    nong = np.flatnonzero(~ground)
    classes[nong] = vegetation_class(hag[nong])
    # 1. noise
    if len(nong):
        counts = cKDTree(xyz[nong]).query_ball_point(xyz[nong], r=cfg.noise_radius,
                                                     return_length=True, workers=-1)
        noise = (counts - 1 < cfg.noise_min_neighbours) | (hag[nong] < -BELOW_GROUND_NOISE)
        classes[nong[noise]] = NOISE
        nong = nong[~noise]
    cand = nong[hag[nong] >= cfg.min_height]
    t1 = time.perf_counter()
    objects: list[ObstacleObject] = []
    if len(cand) >= 3:
        lin, plan, axis_z, normal_z = pca_features(xyz[cand])
        # 2. wires
        wire_like = ((lin > cfg.wire_linearity)
                     & (axis_z < np.sin(np.radians(cfg.wire_max_slope)))
                     & (hag[cand] > cfg.wire_min_clearance))
        wl = np.flatnonzero(wire_like)
        wl = wl[_empty_below(xyz, cand[wl], cand[~wire_like])]
        is_wire = np.zeros(len(cand), bool)
        if len(wl):
            runs = voxel_components(xyz[cand[wl]], 2.0)
            for r in np.unique(runs):
                pts = xyz[cand[wl[runs == r]]]
                if np.linalg.norm(np.ptp(pts[:, :2], axis=0)) >= WIRE_MIN_RUN:
                    is_wire[wl[runs == r]] = True
        classes[cand[is_wire]] = WIRE
        t2 = time.perf_counter()
        # 3. objects of the rest, plus wire runs as objects
        wire_xyz = xyz[cand[is_wire]]
        wire_tree = cKDTree(wire_xyz) if len(wire_xyz) else None
        wire_xy_tree = cKDTree(wire_xyz[:, :2]) if len(wire_xyz) else None
        rest = np.flatnonzero(~is_wire)
        tower_feet: list[np.ndarray] = []
        labels = voxel_components(xyz[cand[rest]], cfg.cluster_distance)
        next_id = 0
        order = np.argsort(labels, kind="stable")
        bounds = np.flatnonzero(np.diff(labels[order])) + 1
        for members in np.split(order, bounds):
            if len(members) < cfg.min_points:
                continue
            local = rest[members]
            pid = cand[local]
            p, h = xyz[pid], hag[pid]
            height = float(h.max())
            extent = float(np.linalg.norm(np.ptp(p[:, :2], axis=0)))
            cls = None
            if height > cfg.tower_min_height and wire_tree is not None:
                # A tower carries wires: they end at its arms, at or below its top (a tree
                # under the line stays below the wires next to it). Trees touching the
                # tower join its component, so only the column around its top is tower.
                top = p[h > 0.7 * height, :2].mean(axis=0)
                column = np.linalg.norm(p[:, :2] - top, axis=1) < TOWER_RADIUS * height
                dist, nearest = wire_tree.query(p[column], distance_upper_bound=TOWER_WIRE_GAP)
                hit = np.isfinite(dist)
                col_top = p[column, 2].max()
                over = wire_xy_tree.query_ball_point(p[column & (h > 0.5 * height), :2],
                                                     r=TOWER_WIRE_GAP, return_sorted=False)
                over_ids = np.unique(np.concatenate([np.asarray(o, np.int64) for o in over]
                                                    or [np.zeros(0, np.int64)]))
                wire_above = (wire_xyz[over_ids, 2] > col_top + 1.0).any() if len(over_ids) \
                    else False
                if hit.any() and not wire_above:
                    classes[pid[column]] = TOWER
                    tower_feet.append(p[column & (h < 0.3 * height)])
                    object_id[pid] = next_id
                    next_id += 1
                    continue
            if cls is None and extent < 2.0 and height > 3.0:
                cls = UNCLASSIFIED
            if cls is None and len(p) >= 10:
                # The paper's RANSAC plane segmentation: a building's main roof plane holds a
                # large share of its points; a crown's best plane holds few.
                roof = ransac_plane(p, distance_threshold=cfg.building_plane_threshold,
                                    max_trials=200, rng=rng, max_tilt_deg=60.0)
                if roof.plane is not None and roof.inliers.mean() >= PLANAR_SHARE:
                    cells = np.unique(np.floor(p[roof.inliers, :2]).astype(np.int64), axis=0)
                    if len(cells) >= cfg.building_min_area:
                        cls = BUILDING
            if cls is not None:
                classes[pid] = cls
            object_id[pid] = next_id
            next_id += 1
        # Tower legs stand on the ground: their lowest points are within the ground filter's
        # band, but a UAV must never take them for ground.
        for feet in tower_feet:
            # only a tower's own base (a lattice base is at most ~15 m across)
            if len(feet) and np.ptp(feet[:, :2], axis=0).max() <= TOWER_BASE_MAX:
                lo_xy, hi_xy = feet[:, :2].min(axis=0) - 0.5, feet[:, :2].max(axis=0) + 0.5
                inside = np.all((xyz[:, :2] >= lo_xy) & (xyz[:, :2] <= hi_xy), axis=1)
                classes[inside & (classes == GROUND)] = TOWER
        wire_ids = cand[is_wire]
        if len(wire_ids):
            runs = voxel_components(xyz[wire_ids], 2.0)
            object_id[wire_ids] = next_id + runs
        t3 = time.perf_counter()
        objects = _objects(xyz, hag, classes, object_id)
    else:
        t2 = t3 = time.perf_counter()
    t4 = time.perf_counter()
    return ObstacleClasses(classes, object_id, tuple(objects),
                           {"noise": t1 - t0, "wires": t2 - t1, "objects": t3 - t2,
                            "summaries": t4 - t3, "total": t4 - t0})


def _objects(xyz: np.ndarray, hag: np.ndarray, classes: np.ndarray,
             object_id: np.ndarray) -> list[ObstacleObject]:
    """Boxes of the objects, vectorised over points (one pass per statistic)."""
    sel = np.flatnonzero(object_id >= 0)
    if len(sel) == 0:
        return []
    ids, inv, counts = np.unique(object_id[sel], return_inverse=True, return_counts=True)
    k = len(ids)
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    for a in range(3):
        np.minimum.at(lo[:, a], inv, xyz[sel, a])
        np.maximum.at(hi[:, a], inv, xyz[sel, a])
    sums = np.stack([np.bincount(inv, xyz[sel, a], k) for a in range(3)], axis=1)
    hmax = np.full(k, -np.inf)
    hmin = np.full(k, np.inf)
    np.maximum.at(hmax, inv, hag[sel])
    np.minimum.at(hmin, inv, hag[sel])
    # class of an object: its most common point class
    cls_count = np.zeros((k, 256), np.int64)
    np.add.at(cls_count, (inv, classes[sel]), 1)
    cls = cls_count.argmax(axis=1)
    return [ObstacleObject(int(ids[i]), int(cls[i]), int(counts[i]), lo[i], hi[i],
                           sums[i] / counts[i], float(hmax[i]), float(hmin[i]))
            for i in range(k)]


def clearance_grid(xyz: np.ndarray, classes: np.ndarray, height_above_ground: np.ndarray, *,
                   center_xy: np.ndarray, cfg: ClearanceConfig
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Occupancy grid around center_xy: per cell the tallest obstacle above ground scaled to
    0..100 (cfg.max_height -> 100); -1 where no point fell; 0 where only ground/low points.

    Returns (cells (rows, cols) int8, row = y index; origin (2,) lower-left corner, m;
    resolution m)."""
    res = cfg.resolution
    side = max(1, int(round(cfg.size / res)))
    origin = np.floor((np.asarray(center_xy, float) - cfg.size / 2) / res) * res
    cells = np.full((side, side), -1, np.int8)
    ij = np.floor((xyz[:, :2] - origin) / res).astype(np.int64)
    inside = np.all((ij >= 0) & (ij < side), axis=1) & np.isfinite(xyz).all(axis=1)
    if not inside.any():
        return cells, origin, res
    ij = ij[inside]
    flat = ij[:, 1] * side + ij[:, 0]
    obstacle = ~np.isin(classes[inside], (GROUND, NOISE))
    h = np.where(obstacle, np.nan_to_num(height_above_ground[inside].astype(float), nan=0.0), 0.0)
    top = np.full(side * side, -1.0)
    np.maximum.at(top, flat, np.maximum(h, 0.0))
    seen = top >= 0
    value = np.full(side * side, -1, np.int8)
    value[seen] = np.clip(np.round(100.0 * top[seen] / cfg.max_height), 0, 100).astype(np.int8)
    return value.reshape(side, side), origin, res
