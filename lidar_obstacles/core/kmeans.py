"""K-means ground extraction for the DEM (Zhao et al. 2019, methods.md section 2).

The paper standardises intensity, runs K-means for k = 1..l, picks k at the elbow of the
SSE curve, keeps the lowest SSE of many restarts, chooses the ground cluster by eye and
removes outliers by building TINs repeatedly. Here every step is automatic:

- ``standardise``: zero mean, unit standard deviation (N - 1 in the denominator).
- ``kmeans``: K-means++ seeding and Lloyd iterations, ``restarts`` runs, lowest SSE kept.
  One-dimensional features (intensity) take an exact fast path: the data are reduced to
  their sorted distinct values with counts, clusters of sorted 1-D data are intervals, so
  an iteration costs O(k log n) with prefix sums instead of O(n k).
- ``elbow_kmeans``: the SSE sweep and the knee as the point farthest below the chord of the
  normalised curve (Kneedle).
- ``kmeans_ground``: the ground cluster is the one whose points lie lowest above the local
  minimum of the cloud (ground is the lower envelope; vegetation, roofs and wires sit above
  it), then ``tin_outlier_filter`` removes spikes and pits and ``lower_envelope_filter``
  the low patches (hedges, cars) that cluster with the ground; finally points of other
  clusters lying on the ground's TIN join it. On AHN4 (156 478 points) the ground's
  precision / recall against the labels went, with the paper's neighbour checks alone ->
  with all three steps, from 0.631 / 0.853 -> 0.923 / 0.992 (intensity) and
  0.848 / 0.970 -> 0.938 / 0.998 (geometric); on ISPRS samp31 the recall from 0.78 to 0.94.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError, cKDTree

from lidar_obstacles.config import KmeansConfig
from lidar_obstacles.core.arrays import (column_min, lowest_per_cell, points_xyz, thread_pools,
                                         tree_query)
from lidar_obstacles.core.interpolate import idw, neighbour_residual, tin
from lidar_obstacles.errors import CloudFormatError

log = logging.getLogger(__name__)
_warned: set[str] = set()  # reasons already logged: a stream of messages warns once

# A "real" intensity has many levels; fewer distinct values than this means a flag or a
# constant (ISPRS samples repeat the label in intensity, the AHN corridor has zeros).
MIN_INTENSITY_LEVELS = 8

# The seed of K-means++'s draws when the caller gives none: fixed, so the same features
# give the same clusters in every run (kmeans_ground and simplify pass their own
# generator, from their config's seed). None draws from fresh entropy instead.
KMEANS_SEED = 0


def standardise(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero-mean, unit-variance copy of each column: (t - mean) / std, std with N - 1.

    values: (N,) or (N, D) numbers. Returns (standardised float64 of the same shape,
    mean (D,), std (D,)). A constant column (or N < 2) has std reported as 0 and is
    returned as zeros, so it cannot dominate or break a distance.
    """
    arr = np.asarray(values, dtype=np.float64)
    flat = arr.reshape(len(arr), -1)
    mean = flat.mean(axis=0) if len(flat) else np.zeros(flat.shape[1])
    std = flat.std(axis=0, ddof=1) if len(flat) > 1 else np.zeros(flat.shape[1])
    safe = np.where(std > 0, std, 1.0)
    out = (flat - mean) / safe
    out[:, std == 0] = 0.0
    return out.reshape(arr.shape), mean, std


@dataclass(frozen=True)
class KmeansResult:
    """The best of the restarts of one K-means.

    labels: (N,) int32 cluster of each sample. centres: (k, D) float64. sse: within-cluster
    sum of squared distances. n_iter: Lloyd iterations of the kept run.
    """

    labels: np.ndarray
    centres: np.ndarray
    sse: float
    n_iter: int

    @property
    def k(self) -> int:
        """The number of clusters (rows of ``centres``)."""
        return len(self.centres)


def _kmeanspp_1d(xs: np.ndarray, w: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Greedy K-means++ seeds of weighted sorted 1-D values: each new centre is the best
    (lowest potential) of 2 + ln(k) candidates drawn with probability ~ w D^2, as in
    scikit-learn; plain K-means++ left Lloyd in poorer minima (SSE up to 3 % higher)."""
    trials = 2 + int(np.log(k))
    cw = np.cumsum(w)
    first = min(int(np.searchsorted(cw, rng.random() * cw[-1], side="right")), len(xs) - 1)
    centres = [xs[first]]
    d2 = (xs - centres[0]) ** 2
    for _ in range(1, k):
        cum = np.cumsum(w * d2)
        if cum[-1] <= 0:  # fewer distinct values than k: repeat one, it ends up empty
            centres.append(centres[-1])
            continue
        picks = np.minimum(np.searchsorted(cum, rng.random(trials) * cum[-1], side="right"),
                           len(xs) - 1)
        cand = np.minimum(d2[None, :], (xs[None, :] - xs[picks, None]) ** 2)
        best = int(np.argmin(cand @ w))
        centres.append(xs[picks[best]])
        d2 = cand[best]
    return np.sort(np.asarray(centres, dtype=np.float64))


def _lloyd_1d(xs: np.ndarray, prefix: tuple[np.ndarray, np.ndarray, np.ndarray],
              centres: np.ndarray, max_iter: int,
              shift_tol: float) -> tuple[np.ndarray, float, int]:
    """Exact Lloyd iterations on sorted distinct values with prefix sums of w, w x, w x^2.

    Clusters of sorted 1-D data are intervals bounded by the midpoints between sorted
    centres, so sums per cluster are differences of prefix sums.
    """
    cw, cs, cq = prefix
    n_iter = 0
    for n_iter in range(1, max_iter + 1):
        bounds = np.searchsorted(xs, 0.5 * (centres[:-1] + centres[1:]))
        edges = np.concatenate([[0], bounds, [len(xs)]])
        wsum = cw[edges[1:]] - cw[edges[:-1]]
        ssum = cs[edges[1:]] - cs[edges[:-1]]
        new = np.where(wsum > 0, ssum / np.where(wsum > 0, wsum, 1.0), centres)
        new.sort()
        shift = float(np.sum((new - centres) ** 2))
        centres = new
        if shift <= shift_tol:
            break
    bounds = np.searchsorted(xs, 0.5 * (centres[:-1] + centres[1:]))
    edges = np.concatenate([[0], bounds, [len(xs)]])
    wsum = cw[edges[1:]] - cw[edges[:-1]]
    ssum = cs[edges[1:]] - cs[edges[:-1]]
    qsum = cq[edges[1:]] - cq[edges[:-1]]
    sse = float(np.sum(qsum - np.where(wsum > 0, ssum ** 2 / np.where(wsum > 0, wsum, 1.0), 0.0)))
    return centres, max(sse, 0.0), n_iter


def _kmeans_1d(x: np.ndarray, k: int, restarts: int, max_iter: int, tol: float,
               rng: np.random.Generator) -> KmeansResult:
    xs, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    w = counts.astype(np.float64)
    zero = np.zeros(1)
    prefix = (np.concatenate([zero, np.cumsum(w)]), np.concatenate([zero, np.cumsum(w * xs)]),
              np.concatenate([zero, np.cumsum(w * xs * xs)]))
    shift_tol = tol * float(np.var(x))
    runs = [_lloyd_1d(xs, prefix, _kmeanspp_1d(xs, w, k, rng), max_iter, shift_tol)
            for _ in range(restarts)]
    centres, sse, n_iter = min(runs, key=lambda run: run[1])
    labels_distinct = np.searchsorted(0.5 * (centres[:-1] + centres[1:]), xs, side="right")
    return KmeansResult(labels=labels_distinct[inverse].astype(np.int32),
                        centres=centres[:, None], sse=sse, n_iter=n_iter)


def _kmeans_nd(x: np.ndarray, k: int, restarts: int, max_iter: int, tol: float,
               rng: np.random.Generator) -> KmeansResult:
    """Several features: scikit-learn's KMeans (Cython Lloyd). A vectorised NumPy Lloyd
    with the same seeding took 2-5x longer on 10 000 x 3 features (0.06 s vs 0.03 s for
    k = 4, 0.13 s vs 0.03 s for k = 10, 10 restarts), so only the one-feature case, where
    sorting makes Lloyd exact and O(k log n), has its own code. scikit-learn runs in ONE
    thread: its OpenMP threads spin-wait, and on a machine whose cores are busy (the
    obstacle detector runs beside this) the sweep on 20 000 x 3 took 35 s instead of 0.6 s.
    """
    from sklearn.cluster import KMeans

    # (the pools found once per process, with scikit-learn's OpenMP runtime among them)
    with thread_pools("sklearn.cluster").limit(limits=1):
        model = KMeans(n_clusters=k, init="k-means++", n_init=restarts, max_iter=max_iter,
                       tol=tol, random_state=int(rng.integers(2**31 - 1))).fit(x)
    return KmeansResult(labels=model.labels_.astype(np.int32),
                        centres=np.asarray(model.cluster_centers_, dtype=np.float64),
                        sse=float(model.inertia_), n_iter=int(model.n_iter_))


def kmeans(x: np.ndarray, k: int, *, restarts: int = 10, max_iter: int = 300,
           tol: float = 1e-4, rng: np.random.Generator | int | None = KMEANS_SEED) -> KmeansResult:
    """K-means (squared Euclidean) with K-means++ seeding, best of ``restarts`` runs.

    x: (N,) or (N, D) float features (standardise them first). k: clusters, 1 <= k <= N.
    One feature: the exact sorted-prefix-sum Lloyd of this module; several: scikit-learn.
    A run stops after ``max_iter`` Lloyd iterations or when the summed squared centre shift
    is below ``tol`` times the mean feature variance (scikit-learn's convention).
    Deterministic for a given seed / Generator. Raises CloudFormatError for bad input.
    """
    arr = np.asarray(x)
    one_feature = arr.ndim == 1
    arr = points_xyz(arr[:, None] if one_feature else arr,
                     "kmeans: x (one feature, as a column)" if one_feature else "kmeans: x",
                     columns=None, min_points=1)
    if not 1 <= k <= len(arr):
        raise CloudFormatError(f"kmeans: k={k} must be between 1 and N={len(arr)}")
    if restarts < 1 or max_iter < 1:
        raise CloudFormatError(f"kmeans: restarts={restarts} and max_iter={max_iter} must be >= 1")
    gen = np.random.default_rng(rng)
    if arr.shape[1] == 1:
        return _kmeans_1d(arr[:, 0], k, restarts, max_iter, tol, gen)
    return _kmeans_nd(arr, k, restarts, max_iter, tol, gen)


def knee_index(values: np.ndarray) -> int:
    """Index of the knee of a decreasing curve: farthest below the chord (Kneedle).

    values: (K,) e.g. the SSE for k = 1..K. Both axes are scaled to [0, 1]; the knee is the
    point with the largest vertical distance below the straight line from the first to
    the last point. A flat curve (no decrease) gives 0.
    """
    y = np.asarray(values, dtype=np.float64)
    if len(y) < 3 or not y[0] > y.min():
        return 0
    yn = (y - y.min()) / (y[0] - y.min())
    xn = np.linspace(0.0, 1.0, len(y))
    return int(np.argmax((1.0 - xn) - yn))


@dataclass(frozen=True)
class ElbowResult:
    """K-means with k chosen at the elbow. sse: (K,) best SSE for k = 1..K, K <= max_k (the
    sweep stops once the SSE reaches 0: more clusters cannot do better)."""

    k: int
    sse: np.ndarray
    result: KmeansResult


def elbow_kmeans(x: np.ndarray, *, max_k: int = 10, restarts: int = 10, max_iter: int = 300,
                 tol: float = 1e-4, sample_size: int = 20_000,
                 rng: np.random.Generator | int | None = KMEANS_SEED) -> ElbowResult:
    """Run :func:`kmeans` for k = 1..max_k and return the clustering at the elbow.

    x: (N,) or (N, D) standardised features. The knee is found on log(SSE): the SSE of
    K-means falls roughly geometrically with k, so on a linear scale the first split
    dominates the curve and the chord's knee lands too early (k = 3 for four
    well-separated intensity classes; 4 on the log scale). Several features and more
    than ``sample_size`` samples: the sweep runs on a random subset of that size and every
    sample then joins its nearest centre (the SSE curve is the subset's). The sweep stops
    early once the SSE is 0, or at as many centres as distinct samples (scikit-learn's SSE
    there is ~1e-30, and each k beyond it printed a ConvergenceWarning); the knee is then
    of the curve as the whole sweep would have made it, the last SSE on to max_k (of a
    curve ending at its first 0 it was k = 1: 4 distinct rows, 3 separated values).
    Deterministic for a given seed.
    """
    gen = np.random.default_rng(rng)
    arr = np.asarray(x, dtype=np.float64)
    fit = arr
    if arr.ndim == 2 and arr.shape[1] > 1 and len(arr) > sample_size:
        fit = arr[gen.choice(len(arr), sample_size, replace=False)]
    last = max(1, min(max_k, len(fit)))
    # (one feature: the SSE reaches 0 there exactly)
    distinct = len(np.unique(fit, axis=0)) if fit.ndim == 2 and fit.shape[1] > 1 else last
    results: list[KmeansResult] = []
    for k in range(1, min(last, distinct) + 1):
        results.append(kmeans(fit, k, restarts=restarts, max_iter=max_iter, tol=tol, rng=gen))
        if results[-1].sse <= 0.0:
            break
    sse = np.array([r.sse for r in results])
    curve = np.concatenate([sse, np.full(last - len(sse), sse[-1])])
    best = (knee_index(np.log(curve + 1e-12 * curve[0] + 1e-300)) if len(curve) >= 3
            else len(curve) - 1)
    best = min(best, len(results) - 1)  # (the first of the equal last ones at most)
    chosen = results[best]
    if fit is not arr:
        centres = chosen.centres
        labels = np.argmin(((arr[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        chosen = KmeansResult(labels=labels.astype(np.int32), centres=centres, sse=chosen.sse,
                              n_iter=chosen.n_iter)
    return ElbowResult(k=best + 1, sse=sse, result=chosen)


# --------------------------------------------------------------------------- ground


def height_above_local_min(xyz: np.ndarray, window: float) -> np.ndarray:
    """(N,) float64: z minus the lowest z within about ``window`` metres (a 3 x 3 block of
    window/2 cells around the point's cell). The lower envelope of the cloud is ground."""
    cell = max(window / 2.0, 1e-6)
    ij = np.floor((xyz[:, :2] - xyz[:, :2].min(axis=0)) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1)
    flat = np.ravel_multi_index((ij[:, 0], ij[:, 1]), shape)
    lowest = np.full(int(np.prod(shape)), np.inf)
    np.minimum.at(lowest, flat, xyz[:, 2])
    lowest = ndimage.minimum_filter(lowest.reshape(shape), size=3, mode="nearest").ravel()
    return xyz[:, 2] - lowest[flat]


def geometric_features(xyz: np.ndarray, *, window: float, neighbours: int = 10) -> np.ndarray:
    """(N, 3) float64 per-point features for clustering without intensity.

    Columns: height above the local minimum (m), roughness = sqrt of the smallest
    eigenvalue of the k-neighbourhood covariance (m), and |normal z| of that neighbourhood.
    Ground is low, smooth and level; vegetation rough; roofs high; walls steep.
    """
    n = len(xyz)
    k = int(min(neighbours, n))
    _, idx = tree_query(cKDTree(xyz), xyz, k=k, workers=-1)
    idx = idx.reshape(n, k)
    nb = xyz[idx] - xyz[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb) / max(k - 1, 1)
    evals, evecs = np.linalg.eigh(cov)
    rough = np.sqrt(np.maximum(evals[:, 0], 0.0))
    normal_z = np.abs(evecs[:, 2, 0])
    return np.column_stack([height_above_local_min(xyz, window), rough, normal_z])


def tin_outlier_filter(xyz: np.ndarray, *, threshold: float, max_rounds: int) -> np.ndarray:
    """(N,) bool: points kept after repeated TIN checks (the paper's outlier removal).

    Each round triangulates the kept points in XY, predicts every point from its Delaunay
    neighbours (inverse-distance mean) and drops the points whose |residual| exceeds
    ``threshold`` (m) and is the largest in their neighbourhood (a spike makes its
    neighbours' residuals large too, so only the local extreme goes and the others are
    judged again on the next TIN), and every point off by more than 4 x threshold. Stops
    when nothing is dropped or after ``max_rounds``.
    Fewer than 4 points or a degenerate (collinear) set: nothing is dropped.
    """
    keep = np.ones(len(xyz), dtype=bool)
    for _ in range(max_rounds):
        idx = np.flatnonzero(keep)
        if len(idx) < 4:
            break
        pts = xyz[idx]
        try:
            tri = Delaunay(pts[:, :2] - pts[:, :2].mean(axis=0))  # centred: conditioning
        except (QhullError, ValueError):
            break
        indptr, nbrs = tri.vertex_neighbor_vertices
        resid = neighbour_residual(pts, indptr, nbrs)
        # largest neighbour residual per point: owners are sorted, so one reduceat
        counts = np.diff(indptr)
        nb_max = np.zeros(len(idx))
        if len(nbrs):
            starts = np.minimum(indptr[:-1], len(nbrs) - 1)
            nb_max = np.where(counts > 0, np.maximum.reduceat(resid[nbrs], starts), 0.0)
        # Gross outliers (4x the threshold) go at once: a patch of them (a tree with no
        # ground below it) would otherwise only lose its top point each round.
        drop = ((resid > threshold) & (resid >= nb_max)) | (resid > 4.0 * threshold)
        if not drop.any():
            break
        keep[idx[drop]] = False
    return keep


def lower_envelope_filter(xyz: np.ndarray, *, cell: float, threshold: float) -> np.ndarray:
    """(N,) bool: points kept because they lie near the TIN of the lowest point per cell.

    Low objects that K-means puts with the ground (hedges, cars, low roofs: smooth,
    level, only a metre or two up) come in patches, which the neighbour-residual check
    cannot see. Their cells' lowest points are on the ground, so a point more than
    ``threshold`` above the TIN of the per-cell minima is dropped. The minima of ground
    on a plane, however steep, lie on that plane, so slopes cost nothing; only ridges and
    hilltops sharper than the cell lose points. Outside the minima's hull the 3 nearest
    minima stand in for the TIN; fewer than 4 points are all kept. cell, threshold:
    metres.
    """
    n = len(xyz)
    if n < 4:
        return np.ones(n, dtype=bool)
    lowest = lowest_per_cell(xyz, column_min(xyz[:, :2]), cell)
    surface = tin(xyz[lowest, :2], xyz[lowest, 2], xyz[:, :2])
    # Beyond the minima's hull (the survey's rim) the 3 nearest minima stand in for the
    # TIN: on AHN4 this took the intensity ground's precision from 0.77 to 0.92 (roofs
    # cut by the tile edge); it costs rim points on steep slopes (slope x distance to
    # the nearest minimum above the threshold).
    outside = np.isnan(surface)
    if outside.any():
        surface[outside] = idw(xyz[lowest, :2], xyz[lowest, 2], xyz[outside, :2],
                               neighbours=3)
    return ~(xyz[:, 2] - surface > threshold)


@dataclass(frozen=True)
class KmeansGround:
    """Ground found by K-means.

    ground: (N,) bool final ground (after the TIN checks: :func:`tin_outlier_filter`, then
    :func:`lower_envelope_filter`, then every point within ``densify_distance`` of the
    TIN of what is left). candidates: (N,) bool the chosen cluster(s) before.
    features: what was clustered (`intensity`, `two_stage` or `geometric`). k: clusters at
    the elbow (first stage for two_stage). sse: (K,) the elbow curve. cluster_height: (k,)
    median height above the local minimum of each (first-stage) cluster (m).
    ground_clusters: the clusters taken as ground (empty for two_stage, whose ground
    gathers classes inside each first-stage cluster). reason: why the requested features
    were not used ("" when they were).
    """

    ground: np.ndarray
    candidates: np.ndarray
    features: str
    k: int
    sse: np.ndarray
    cluster_height: np.ndarray
    ground_clusters: tuple[int, ...]
    reason: str = ""


def intensity_problem(intensity: np.ndarray | None) -> str:
    """Why an (N,) intensity array cannot be clustered on ("" when it can)."""
    if intensity is None:
        return "no intensity given"
    levels = len(np.unique(np.asarray(intensity)))
    if levels < MIN_INTENSITY_LEVELS:
        return (f"intensity has only {levels} distinct value(s), fewer than "
                f"{MIN_INTENSITY_LEVELS}: constant or a flag, not a measurement")
    return ""


def _cluster_heights(labels: np.ndarray, k: int, height: np.ndarray) -> np.ndarray:
    """(k,) median of ``height`` per cluster (inf for an empty cluster)."""
    out = np.full(k, np.inf)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(k + 1))
    sorted_h = height[order]
    for c in range(k):  # k <= 30 clusters
        if bounds[c + 1] > bounds[c]:
            out[c] = float(np.median(sorted_h[bounds[c]:bounds[c + 1]]))
    return out


def kmeans_ground(xyz: np.ndarray, *, cfg: KmeansConfig, intensity: np.ndarray | None = None,
                  rng: np.random.Generator | int | None = None) -> KmeansGround:
    """Ground points by K-means clustering (the paper's method, with automatic choices).

    xyz: (N, 3) float64 metres. intensity: (N,) only when the caller knows it is a real
    measured intensity (pass None for ISPRS, whose intensity repeats the label); an
    intensity with fewer than 8 distinct values is treated as absent. When intensity is
    absent the clustering runs on :func:`geometric_features`, ``reason`` says why and a
    warning is logged (once per distinct reason in a process, so a stream of messages
    does not repeat it). rng defaults to ``cfg.seed``.
    """
    xyz = points_xyz(xyz, "kmeans_ground")
    n = len(xyz)
    gen = np.random.default_rng(cfg.seed if rng is None else rng)
    if n < 4:
        all_ground = np.ones(n, dtype=bool)
        return KmeansGround(all_ground, all_ground, cfg.features, 1, np.zeros(1),
                            np.zeros(1), (0,), reason=f"only {n} points: all taken as ground")
    height = height_above_local_min(xyz, cfg.ground_window)
    features, reason = cfg.features, ""
    if features in ("intensity", "two_stage"):
        reason = intensity_problem(intensity)
        if reason:
            if reason not in _warned:
                _warned.add(reason)
                log.warning("kmeans ground: %s; clustering on geometric features instead",
                            reason)
            features = "geometric"
    sweep: dict[str, Any] = dict(max_k=cfg.max_k, restarts=cfg.restarts, max_iter=cfg.max_iter,
                                 tol=cfg.tol, sample_size=cfg.sample_size, rng=gen)
    if features == "two_stage":
        # Stage 1 splits the survey into compact XYZ blobs; stage 2 clusters intensity
        # inside each blob and takes its low classes, so blobs of pure roof or canopy
        # contribute nothing.
        first = elbow_kmeans(standardise(xyz)[0], **sweep)
        labels1 = first.result.labels
        candidates = np.zeros(n, dtype=bool)
        for c in range(first.k):
            members = np.flatnonzero(labels1 == c)
            if len(members) < 2:
                continue
            second = elbow_kmeans(standardise(np.asarray(intensity)[members])[0], **sweep)
            heights = _cluster_heights(second.result.labels, second.k, height[members])
            low = np.flatnonzero(heights <= cfg.ground_max_height)
            candidates[members[np.isin(second.result.labels, low)]] = True
        k, sse = first.k, first.sse
        cluster_height = _cluster_heights(labels1, first.k, height)
        ground_clusters: tuple[int, ...] = ()
    else:
        feats = (intensity if features == "intensity"
                 else geometric_features(xyz, window=cfg.ground_window))
        elbow = elbow_kmeans(standardise(np.asarray(feats, dtype=np.float64))[0], **sweep)
        cluster_height = _cluster_heights(elbow.result.labels, elbow.k, height)
        # Every class lying near the local minimum is ground (intensity splits ground
        # into several classes, e.g. asphalt and grass); at least the lowest one is.
        chosen = np.flatnonzero(cluster_height <= cfg.ground_max_height)
        if len(chosen) == 0:
            chosen = np.array([int(np.argmin(cluster_height))])
        ground_clusters = tuple(int(c) for c in chosen)
        candidates = np.isin(elbow.result.labels, chosen)
        k, sse = elbow.k, elbow.sse
    idx = np.flatnonzero(candidates)
    idx = idx[tin_outlier_filter(xyz[idx], threshold=cfg.tin_threshold,
                                 max_rounds=cfg.tin_rounds)]
    idx = idx[lower_envelope_filter(xyz[idx], cell=cfg.ground_window,
                                    threshold=cfg.tin_threshold)]
    ground = np.zeros(n, dtype=bool)
    ground[idx] = True
    if cfg.densify_distance > 0 and len(idx) >= 3:
        # Ground that K-means put in another cluster (bright asphalt among dark grass,
        # steep ground among rough classes) lies on the surface the kept ground spans.
        rest = np.flatnonzero(~ground)
        surface = tin(xyz[idx, :2], xyz[idx, 2], xyz[rest, :2])
        ground[rest[np.abs(xyz[rest, 2] - surface) <= cfg.densify_distance]] = True
    return KmeansGround(ground=ground, candidates=candidates, features=features, k=k, sse=sse,
                        cluster_height=cluster_height, ground_clusters=ground_clusters,
                        reason=reason)
