"""Point-cloud simplification by K-means++ on normals (Li et al. 2020, methods.md section 3).

The paper: keep first returns, standardise X, Y, Z and intensity, K-neighbourhoods (K = 10)
from a KD-tree, PCA normals, the elbow picks k (8 on its desert), K-means++ with 100
restarts; each normal cluster is a candidate simplified cloud, and the one whose Delaunay
TIN, rasterised on 0.125 m cells, correlates best with the raster of all points is kept
(81.833 % reduction, r = 0.890). Here:

- ``pca_normals``: K-neighbourhood PCA normals, vectorised, oriented z >= 0 (the checked
  public face of the normals ``simplify`` computes).
- ``tin_raster_correlation``: the paper's validation, with a linear TIN (``simplify``
  validates the same way, the full cloud's raster made once for all its candidates).
- ``simplify`` with ``method="normal_cluster"``: the paper's protocol, its by-eye step made
  automatic (below); ``method="normal_space"``: the improvement, ``keep`` of the points
  spread over every normal cluster AND over space (one representative per normal cluster
  per voxel), so roof slopes, walls and ground all stay and cover the extent evenly.

Reading of the paper where methods.md is silent:

- Standardisation. The paper standardises X, Y, Z and intensity (zero mean, unit standard
  deviation, N - 1) and Table 3 lists the neighbourhood in those units, but its normals
  are the PCA of a local plane in X, Y, Z (intensity has no part in a plane). Standardising
  X, Y, Z per axis stretches the scene (z by sigma_xy / sigma_z: 3-10x on a survey tile)
  and makes a normal depend on the extent of the message, which a stream of overlapping
  clouds cannot have. Measured (56 000-point crops, first returns; r of the best
  cluster / of normal_space at 18 %), metric vs standardised X, Y, Z: AHN4 k 5 vs 5,
  0.980 / 0.977 vs 0.976 / 0.976; ISPRS samp11 k 5 vs 5, 0.998 / 0.998 vs 0.997 / 0.998.
  No gain, so normals are computed in metres. Intensity is not used; ``reason`` says so
  when one is given.
- Orientation. MATLAB's PCA returns each eigenvector with an arbitrary sign; K-means on
  such normals splits one surface into two antipodal clusters. Airborne data are seen
  from above, so every surface the sensor saw faces up: normals are flipped to z >= 0.
- The choice among clusters. The paper picked clusters 1-3 "by visual interpretation",
  which were its three largest (lowest reduction: "more points express the details
  better"), computed r for those and kept the highest r. Here: the ``_SHORTLIST`` largest
  clusters are validated and the highest r wins.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from lidar_obstacles.core.arrays import (eigenvector3, points_xyz, symmetric_eigenvalues3,
                                         tree_query)
from lidar_obstacles.config import SimplifyConfig
from lidar_obstacles.core.ground import far_points
from lidar_obstacles.core.interpolate import tin
from lidar_obstacles.core.kmeans import elbow_kmeans
from lidar_obstacles.core.metrics import raster_correlation
from lidar_obstacles.errors import CloudFormatError, ConfigError


# The paper validated its three largest clusters (the by-eye shortlist).
_SHORTLIST = 3
# Points per batch of the neighbourhood covariances: (batch, K, 3) float64 stays ~16 MB
# for K = 10 whatever the cloud size.
_BATCH = 65_536
# The validation raster is capped at this many cells (the cell grows beyond): two float64
# rasters of 4 M cells are 64 MB.
_MAX_CELLS = 4_000_000
# Secant steps of the voxel-edge search of voxel_sample (each one np.unique pass).
_SEARCH = 8


class Candidate(NamedTuple):
    """One normal cluster as a candidate simplified cloud (the paper's Table 4/5 rows).

    cluster: label. points: its size. reduction: share of the clustered cloud dropped when
    only this cluster is kept (0..1). r: its TIN raster correlation (NaN: not validated).
    """

    cluster: int
    points: int
    reduction: float
    r: float


@dataclass(frozen=True)
class SimplifyResult:
    """The simplified cloud.

    keep: (N,) bool, the kept points of the input. labels: (N,) int32 normal cluster of
    each point, -1 for points dropped before clustering (later returns) or never clustered
    (degenerate input). k: clusters chosen by the elbow (0 when no clustering ran).
    sse: (<= max_k,) float64 best SSE for k = 1.. (the elbow curve; shorter when the SSE
    reached 0). candidates: ``normal_cluster`` only, one :class:`Candidate` per cluster.
    chosen: the kept cluster (``normal_cluster``) or -1. r: Pearson correlation of the TIN
    raster of the kept points with that of every clustered point (NaN when not computed or
    not computable). reason: "" or why the input was degenerate.
    timings: seconds per step.
    """

    keep: np.ndarray
    labels: np.ndarray
    k: int
    sse: np.ndarray
    candidates: tuple[Candidate, ...] = ()
    chosen: int = -1
    r: float = float("nan")
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------- normals


def _neighbourhood_pca(xyz: np.ndarray, neighbours: int) -> np.ndarray:
    """(N, 3) unit normals, oriented z >= 0, of the ``neighbours`` nearest points of each
    of xyz (N, 3) m (the point itself included, as in the paper's Table 2)."""
    n = len(xyz)
    k = int(min(neighbours, n))
    centred = xyz - xyz.mean(axis=0)  # conditioning: survey coordinates are 1e5-1e6 m
    _, idx = tree_query(cKDTree(centred), centred, k=k, workers=-1)
    idx = np.asarray(idx).reshape(n, k)
    normals = np.empty((n, 3))
    rows, cols = np.triu_indices(3)
    for lo in range(0, n, _BATCH):
        nb = centred[idx[lo:lo + _BATCH]]
        nb -= nb.mean(axis=1, keepdims=True)
        # The six distinct products summed over the neighbours: 5x faster than
        # einsum("nki,nkj->nij") on 50 000 x 10 (15 ms vs 89 ms).
        cov = np.empty((len(nb), 3, 3))
        for a, b in zip(rows, cols):
            s = np.einsum("nk,nk->n", nb[:, :, a], nb[:, :, b])
            cov[:, a, b] = s
            cov[:, b, a] = s
        normals[lo:lo + _BATCH] = eigenvector3(cov, symmetric_eigenvalues3(cov)[:, 2])
    # Airborne surfaces are seen from above, so they face up: z >= 0. Exactly horizontal
    # normals (vertical walls to the last bit) take x >= 0, then y >= 0, so a flip is never
    # left to the sign the solver happened to give.
    flip = (normals[:, 2] < 0) | ((normals[:, 2] == 0) & (
        (normals[:, 0] < 0) | ((normals[:, 0] == 0) & (normals[:, 1] < 0))))
    normals[flip] *= -1.0
    return normals


def pca_normals(xyz: np.ndarray, *, neighbours: int) -> np.ndarray:
    """Unit normals from the covariance of each point's K-neighbourhood.

    xyz: (N, 3) float64 metres. neighbours: K, the nearest points (the point itself
    included) whose covariance gives the normal: the eigenvector of its smallest
    eigenvalue. Returns (N, 3) float64 unit vectors oriented z >= 0 (airborne data: the
    sensor saw every surface from above; a normal's sign from PCA is otherwise arbitrary,
    and K-means would split one surface into two antipodal clusters). Fewer points than K
    use all of them. Neighbourhoods that span no plane (coincident or collinear points)
    give some unit vector orthogonal to them. Raises CloudFormatError for NaN or a wrong
    shape.
    """
    arr = points_xyz(xyz, "pca_normals: xyz")
    if neighbours < 1:
        raise ConfigError(f"pca_normals: neighbours={neighbours} must be >= 1")
    if len(arr) == 0:
        return np.zeros((0, 3))
    return _neighbourhood_pca(arr, neighbours)


# --------------------------------------------------------------------------- validation


def mean_spacing(xy: np.ndarray) -> float:
    """sqrt(area of the XY convex hull / N) of (N, 2+) points, metres: the spacing of an
    even sample of the same density. NaN for fewer than 3 points or no area."""
    if len(xy) < 3:
        return float("nan")
    try:
        area = ConvexHull(xy - xy.mean(axis=0)).volume  # 2-D "volume" is the area
    except (QhullError, ValueError):
        return float("nan")
    return float(np.sqrt(area / len(xy))) if area > 0 else float("nan")


def _grid(xy: np.ndarray, cell: float) -> np.ndarray:
    """(M, 2) centres of ``cell`` m cells covering the bounding box of ``xy``."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    shape = np.maximum(np.ceil((hi - lo) / cell), 1).astype(np.int64)
    if int(np.prod(shape)) > _MAX_CELLS:
        cell *= float(np.sqrt(np.prod(shape) / _MAX_CELLS))
        shape = np.maximum(np.ceil((hi - lo) / cell), 1).astype(np.int64)
    gx = lo[0] + (np.arange(shape[0]) + 0.5) * cell
    gy = lo[1] + (np.arange(shape[1]) + 0.5) * cell
    return np.column_stack([np.repeat(gx, len(gy)), np.tile(gy, len(gx))])


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r of two rasters over the cells finite in both (NaN: undefined)."""
    r = raster_correlation(a, b)
    return float("nan") if r is None else r


def tin_raster_correlation(kept_xyz: np.ndarray, all_xyz: np.ndarray, *, cell: float) -> float:
    """The paper's validation: Pearson r between the TIN rasters of two point sets.

    kept_xyz: (M, 3), all_xyz: (N, 3) float64 metres. Each set is triangulated in XY
    (Delaunay) and its z interpolated linearly at the centres of ``cell`` m cells covering
    the bounding box of ``all_xyz``; cells outside either hull (NaN) are skipped. The paper
    rasterised with natural-neighbour interpolation in ArcGIS; linear on the same TIN
    agrees with it at the vertices and differs only inside triangles, far less than the
    triangles of the two sets differ from each other. More than 4 M cells: the cell grows
    to bound memory. Returns NaN when a set spans no surface (fewer than 3 points,
    collinear in XY) or a raster is constant. Raises CloudFormatError for bad arrays.
    """
    kept = points_xyz(kept_xyz, "tin_raster_correlation: kept_xyz")
    full = points_xyz(all_xyz, "tin_raster_correlation: all_xyz")
    if not cell > 0:
        raise ConfigError(f"tin_raster_correlation: cell={cell} must be > 0 m")
    if len(full) < 3 or len(kept) < 3:
        return float("nan")
    grid = _grid(full[:, :2], cell)
    return _pearson(tin(kept[:, :2], kept[:, 2], grid), tin(full[:, :2], full[:, 2], grid))


# --------------------------------------------------------------------------- selection


def _voxel_keys(xyz: np.ndarray, size: float) -> np.ndarray:
    """(N,) int64 voxel index of each point for cubes of ``size`` m."""
    ijk = np.floor((xyz - xyz.min(axis=0)) / size).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def _representatives(xyz: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Index of one point per voxel key: the one nearest its voxel's centroid (a point of
    the cloud, not a synthetic centroid, so every field of it stays true)."""
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, xyz)
    d2 = ((xyz - sums[inverse] / counts[inverse, None]) ** 2).sum(axis=1)
    order = np.lexsort((d2, inverse))
    first = np.r_[True, inverse[order][1:] != inverse[order][:-1]]
    return order[first]


def voxel_sample(xyz: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """(N,) bool: exactly ``count`` points, one per voxel, the voxel edge chosen so that
    about ``count`` voxels are occupied (a voxel grid of a prescribed size).

    xyz: (N, 3) metres. The edge is found by a secant search in log-log (occupied voxels
    fall like edge^-d, d ~ 2 on surfaces), at most ``_SEARCH`` np.unique passes; the
    surplus or shortfall left (within 1 % when the search converges) is settled by
    dropping random representatives or adding random other points.
    """
    n = len(xyz)
    keep = np.zeros(n, dtype=bool)
    count = int(min(max(count, 0), n))
    if count == n:
        keep[:] = True
    if count == 0 or count == n:
        return keep
    spacing = mean_spacing(xyz[:, :2])
    span = float(np.ptp(xyz, axis=0).max())
    if not span > 0:  # all points in one spot: any of them will do
        keep[rng.choice(n, count, replace=False)] = True
        return keep
    size = spacing * np.sqrt(n / count) if np.isfinite(spacing) else span / count
    best = _representatives(xyz, _voxel_keys(xyz, size))
    prev: tuple[float, int] | None = None
    for step in range(_SEARCH):
        reps = best if step == 0 else _representatives(xyz, _voxel_keys(xyz, size))
        m = len(reps)
        if abs(m - count) < abs(len(best) - count):
            best = reps
        if abs(m - count) <= 0.01 * count:
            break
        slope = -2.0  # d log(voxels) / d log(edge) of a surface, until measured
        if prev is not None and prev[1] != m:
            slope = float(np.clip((np.log(m) - np.log(prev[1]))
                                  / (np.log(size) - np.log(prev[0])), -3.0, -0.5))
        prev = (size, m)
        size *= float(np.exp((np.log(count) - np.log(m)) / slope))
    if len(best) > count:
        best = rng.choice(best, count, replace=False)
    keep[best] = True
    short = count - int(keep.sum())
    if short > 0:
        keep[rng.choice(np.flatnonzero(~keep), short, replace=False)] = True
    return keep


def cluster_quotas(sizes: np.ndarray, count: int) -> np.ndarray:
    """(k,) int points to keep per cluster: proportional to ``sizes`` (largest remainders),
    summing to ``count``, and at least 1 for every non-empty cluster when ``count`` allows
    (the last points of a rare orientation are the ones a uniform sample loses)."""
    sizes = np.asarray(sizes, dtype=np.int64)
    count = int(min(count, sizes.sum()))
    share = sizes * (count / max(int(sizes.sum()), 1))
    quota = np.floor(share).astype(np.int64)
    quota[np.argsort(-(share - quota), kind="stable")[:count - int(quota.sum())]] += 1
    for c in np.flatnonzero((sizes > 0) & (quota == 0)):
        if count < np.count_nonzero(sizes):
            break
        donor = int(np.argmax(quota))
        quota[donor] -= 1
        quota[c] = 1
    return quota


def normal_space_sample(xyz: np.ndarray, labels: np.ndarray, count: int,
                        rng: np.random.Generator) -> np.ndarray:
    """(N,) bool: ``count`` points spread over every normal cluster and over space.

    xyz: (N, 3) metres; labels: (N,) int normal cluster >= 0. Every cluster keeps its
    share (:func:`cluster_quotas`), drawn by its own voxel grid (:func:`voxel_sample`), so
    each orientation (ground, each roof slope, walls) keeps the same fraction of its
    points, evenly spread over the extent it covers.

    Measured on 50 000-56 000 first returns (benchmarks/bench_simplify.py has the full
    table), TIN raster r at 18 % / 5 % kept: AHN4 this 0.976 / 0.963, one voxel grid
    over all clusters with a shared edge 0.968 / 0.935 (vegetation, whose normals fall in
    every cluster, got one point per cluster per voxel: k x the density), the same in 2-D
    cells 0.978 / 0.969, a plain 3-D voxel grid 0.971 / 0.952, a plain 2-D grid
    0.981 / 0.976, uniform random 0.970 / 0.958; extra density where the surface
    variation is high (voxel edge halved above 0.005 / 0.02) lowered r by 0.005-0.02,
    and greedy insertion of the points farthest off the TIN was erratic (0.961-0.984).
    The raster r rewards even XY coverage alone; 3-D voxels are kept because walls,
    wires and towers (what a UAV must not hit) keep their height, which r cannot see.
    """
    keep = np.zeros(len(xyz), dtype=bool)
    labels = np.asarray(labels)
    sizes = np.bincount(labels) if len(labels) else np.zeros(0, dtype=np.int64)
    for c, quota in enumerate(cluster_quotas(sizes, count)):
        if quota > 0:  # k <= 30 clusters
            members = np.flatnonzero(labels == c)
            keep[members[voxel_sample(xyz[members], int(quota), rng)]] = True
    return keep


# --------------------------------------------------------------------------- simplify


def _degenerate(xyz: np.ndarray, neighbours: int) -> str:
    n = len(xyz)
    if n < neighbours + 1:
        return f"only {n} points, fewer than neighbours + 1 = {neighbours + 1}: all kept"
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    if s[0] == 0.0:
        return "all points are coincident: all kept"
    if s[1] <= 1e-9 * s[0]:
        return "all points are collinear: no surface has a normal; all kept"
    return ""


def _first_returns(return_number: np.ndarray | None, n: int,
                   use: bool) -> tuple[np.ndarray, str]:
    """(N,) bool of the points to cluster, and a note when return numbers were unusable."""
    if not use or return_number is None:
        return np.ones(n, dtype=bool), ""
    ret = np.asarray(return_number)
    if ret.shape != (n,):
        raise CloudFormatError(f"simplify: return_number has shape {ret.shape}, expected ({n},)")
    if not np.any(ret >= 1):
        # LAS return number 0 is "not recorded" (the AHN corridor tiles): keep everything.
        return np.ones(n, dtype=bool), "return numbers are all 0 (not recorded): all points used"
    return ret <= 1, ""


# The steps `simplify` tells its `progress` of, in order (the last only when it validates).
SIMPLIFY_STEPS = ("normals", "k-means", "selection", "validation")


def simplify(xyz: np.ndarray, *, cfg: SimplifyConfig, return_number: np.ndarray | None = None,
             rng: np.random.Generator | None = None,
             progress: Callable[[str], None] | None = None) -> SimplifyResult:
    """Simplify a cloud by K-means++ clustering of its normals.

    xyz: (N, 3) float64 metres. (No intensity: the paper standardises it with X, Y, Z, but
    a normal is the PCA of a plane in X, Y, Z; see the module docstring.)
    return_number: (N,) ints or None; with ``cfg.first_returns`` only points with return
    number 1 (or 0, not recorded) are clustered and later returns are never kept.
    rng: defaults to ``cfg.seed``; the result is deterministic for a given generator state.
    progress: told the name of each of SIMPLIFY_STEPS as it begins (on a survey of 774 000
    points the validation's two TINs take 12 of 17 s).

    Steps: first returns -> PCA normals of ``cfg.neighbours`` -> elbow over
    k = 1..``cfg.max_k`` (K-means++, ``restarts``, ``max_iter``, ``tol``; swept on at
    most ``sample_size`` normals, then every point joins its nearest centre) -> the kept
    cloud: ``normal_cluster`` the best-correlating of the ``_SHORTLIST`` largest clusters;
    ``normal_space`` ``cfg.keep`` of the points, one per (normal cluster, voxel).
    r is computed when the method needs it or ``cfg.validate`` is set, on
    ``cfg.validation_cell`` m cells (0: the mean point spacing, the paper's 0.125 m on its
    ~70 pts/m2). Degenerate input (fewer than neighbours + 1 points, coincident or
    collinear points) keeps every point with a reason. Raises CloudFormatError for NaN or
    wrong shapes.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    arr = points_xyz(xyz, "simplify: xyz")
    n = len(arr)
    gen = np.random.default_rng(cfg.seed if rng is None else rng)
    clustered, note = _first_returns(return_number, n, cfg.first_returns)
    notes = [note] if note else []
    far = far_points(arr)
    if far.any():  # a stray return kilometres off would make the cloud look like a line
        clustered &= ~far
        notes.append(f"{int(far.sum())} stray points far from the cloud dropped")
    idx = np.flatnonzero(clustered)
    pts = arr[idx]
    labels = np.full(n, -1, dtype=np.int32)
    timings["first_returns"] = time.perf_counter() - t0

    why = _degenerate(pts, cfg.neighbours)
    if why:
        return SimplifyResult(keep=clustered.copy(), labels=labels, k=0, sse=np.zeros(0),
                              r=float("nan"), reason="; ".join([why] + notes),
                              timings=timings)

    def step(name: str) -> None:
        if progress is not None:
            progress(name)

    t = time.perf_counter()
    step("normals")
    normals = _neighbourhood_pca(pts, cfg.neighbours)
    timings["normals"] = time.perf_counter() - t
    t = time.perf_counter()
    step("k-means")
    with warnings.catch_warnings():
        # Planes give many identical normals; for k above their distinct values
        # scikit-learn warns of fewer distinct clusters, which the elbow already handles.
        warnings.filterwarnings("ignore", message="Number of distinct clusters")
        elbow = elbow_kmeans(normals, max_k=cfg.max_k, restarts=cfg.restarts,
                             max_iter=cfg.max_iter, tol=cfg.tol, sample_size=cfg.sample_size,
                             rng=gen)
    cluster = elbow.result.labels
    labels[idx] = cluster
    timings["kmeans"] = time.perf_counter() - t

    cell = cfg.validation_cell if cfg.validation_cell > 0 else mean_spacing(pts[:, :2])
    grid = _grid(pts[:, :2], cell) if np.isfinite(cell) else np.zeros((0, 2))
    reference: np.ndarray | None = None

    def correlation(member: np.ndarray) -> float:
        nonlocal reference
        if len(grid) == 0:
            return float("nan")
        if reference is None:
            reference = tin(pts[:, :2], pts[:, 2], grid)
        sub = pts[member]
        return _pearson(tin(sub[:, :2], sub[:, 2], grid), reference)

    t = time.perf_counter()
    step("selection")
    keep = np.zeros(n, dtype=bool)
    sizes = np.bincount(cluster, minlength=elbow.k)
    candidates: list[Candidate] = []
    chosen, r = -1, float("nan")
    if cfg.method == "normal_cluster":
        step("validation")  # (the shortlisted clusters' correlations choose the cloud)
        shortlist = set(np.argsort(-sizes, kind="stable")[:_SHORTLIST].tolist())
        for c in range(elbow.k):
            rc = correlation(cluster == c) if c in shortlist and sizes[c] > 0 else float("nan")
            candidates.append(Candidate(c, int(sizes[c]), float(1.0 - sizes[c] / len(pts)), rc))
        scored = [cand for cand in candidates if np.isfinite(cand.r)]
        best = max(scored, key=lambda cand: cand.r) if scored else max(
            candidates, key=lambda cand: cand.points)
        chosen, r = best.cluster, best.r
        keep[idx[cluster == chosen]] = True
        timings["validate"] = time.perf_counter() - t
    elif cfg.method == "normal_space":
        chosen_mask = normal_space_sample(pts, cluster, int(round(cfg.keep * len(pts))), gen)
        keep[idx[chosen_mask]] = True
        timings["select"] = time.perf_counter() - t
        if cfg.validate:
            t = time.perf_counter()
            step("validation")
            r = correlation(chosen_mask)
            timings["validate"] = time.perf_counter() - t
    else:
        raise ConfigError(f"simplify: unknown method {cfg.method!r}")
    timings["total"] = time.perf_counter() - t0
    return SimplifyResult(keep=keep, labels=labels, k=elbow.k, sse=elbow.sse,
                          candidates=tuple(candidates), chosen=chosen, r=r,
                          reason="; ".join(notes), timings=timings)
