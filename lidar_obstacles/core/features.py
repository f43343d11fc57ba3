"""Feature points by the Gaussian map of neighbour triangles + K-means (Xu et al. 2019,
methods.md section 4, seed 001).

Per point p_i: its k nearest neighbours; every pair (p_m, p_n) of them makes a triangle
whose unit normal N = p_ip_m x p_ip_n / |.| is a point of the Gaussian sphere, k(k-1)/2 of
them (91 for k = 14). The normals are turned to one side (those more than 90 deg from a
reference flipped) and clustered by K-means with the Manhattan distance (paper eq. 3:
assignment by the L1 distance, centres the arithmetic means, iterated until the labels stop
changing), for k' = 2..max_clusters+1, and k' is the one of the highest mean silhouette
(eq. 4). The paper's reading of the result (2.4): one cluster is a plane (no feature);
2..4 clusters a cylinder, cone, crease or edge (feature); no cluster or more than 4: no
feature.

What the paper leaves open, decided here:

- One cluster: the silhouette is undefined for k' = 1, and the paper does not say how a
  plane is told apart. A point is a plane when all its triangle normals lie within
  `plane_angle` of their mean (plane_angle = 10 deg).
- Clusters "kept" (the paper's word): those holding at least `MIN_CLUSTER_SHARE` of the
  normals; the code is the number kept for the k' of the best silhouette.
- "No cluster kept": the best mean silhouette is below `min_silhouette` (0.5: the usual
  "reasonable structure" bound; a K-means split of one noisy blob of normals scores
  ~0.3-0.45), or too few usable triangles (fewer than 2 (max_clusters + 1)).
- Degenerate triangles (angle at p_i below 5 deg or above 175 deg, coincident points) have
  no normal and are left out: on a wire or a scan line all of them are.
- The orientation reference: the paper takes the normal at the highest point of the "main
  scanned face" for the whole cloud (`reference: highest`). Normals near 90 deg from it
  (walls under a level roof, for an airborne scan) then flip at random and split into two
  antipodal clusters, a false crease; `reference: local` turns them to the point's own PCA
  normal, which lies within 90 deg of both faces of a crease.

Two implementations (`method`), the same decisions otherwise:

- `faithful`: float64, every k' in 2..max_clusters+1, the full silhouette from all
  pairwise Manhattan distances of the normals, (C, P, P) per chunk.
- `fast`: float32, and points whose neighbourhood is plainly flat by PCA (l3 / l2 below
  `FLAT_RATIO`) are planes without their Gaussian map. On noisy data this is also
  the better plane test: a triangle normal from two near neighbours is decided by the
  noise (2 cm noise at 0.25 m spacing: on a face only ~63 % of a point's 91 normals lie
  within 10 deg of their mean), so the faithful plane test rarely passes and K-means
  splits off the stray normals as a "cluster" (faithful precision 0.38 on a noisy box,
  fast 0.98; benchmarks/bench_features.py).
  Measured and left out: the simplified silhouette (distances to the centres, O(P k')
  instead of O(P^2)) saved little, K-means is ~90 % of the time, and it scores higher
  than the full one, so more noisy points passed min_silhouette (AHN4 roofs: 68 % feature
  points against 46 %).

Everything is vectorised over chunks of points, arrays (C, P, 3) for C points and
P = k(k-1)/2 normals; the chunk size follows from a memory budget (`CHUNK_BYTES`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from lidar_obstacles.core.arrays import (eigenvector3, points_xyz, symmetric_eigenvalues3,
                                         tree_query)
from lidar_obstacles.config import FeaturesConfig

NO_CLUSTERS = 0  # cluster code: no clear clusters, or too few neighbours / triangles
PLANE = 1  # cluster code: one cluster of normals

# A triangle whose angle at p_i is below this (or above 180 deg minus it) has no reliable
# normal: |a x b| = |a| |b| sin(angle), so its direction is decided by noise.
MIN_TRIANGLE_ANGLE = 5.0  # deg
MAX_LLOYD = 50  # Lloyd iterations per K-means run; the paper iterates to convergence and
# the runs on 91 normals on the sphere mostly converge in 3-6 (a few take 20+): the cap
# only bounds a cycle.

# Working memory per chunk, roughly: the silhouette holds (C, P, P) pairwise distances
# (66 kB per point at k = 14 in float64, 33 kB in float32) and K-means (C R, P, k')
# arrays; at the defaults (k = 14, max_clusters = 4, restarts = 1) `_chunk_size` gives 146
# points (faithful) or 292 (fast), ~32 MB.
CHUNK_BYTES = 32 * 2**20

# `fast`: l3 / l2 of the point and its k neighbours below which a point is a plane without
# its Gaussian map (l3 / l2 ~ 0 on a plane, ~1 on a line: l3 / sum(l), the usual surface
# variation, is ~0 on a wire too and took every wire point for a plane). Gable roof of
# 20 deg pitch, 0.25 m spacing, noise 2 cm / 5 cm, precision / recall of the feature
# points: 0.02 -> 0.94 / 0.75, 0.31 / 0.55; 0.05 -> 0.99 / 0.68, 0.50 / 0.52;
# 0.1 -> 0.99 / 0.56, 0.85 / 0.45; 0.2 -> 1.00 / 0.28, 0.97 / 0.28.
FLAT_RATIO = 0.05
# The paper's "clusters kept" (保留): a cluster counts when it holds at least this share of
# the point's usable normals; smaller ones are stray normals of noisy triangles. On a box
# with 2 cm noise (fast): 0 -> precision 0.98, recall 0.74 (edge points split into > 4
# clusters); 0.1 -> 0.99 / 0.95; 0.2 -> 1.00 / 0.84.
MIN_CLUSTER_SHARE = 0.1


@dataclass(frozen=True)
class FeatureResult:
    """Gaussian-map feature points of a cloud.

    feature: (N,) bool, the feature points (2..max_clusters clusters of normals).
    clusters: (N,) int8, the number of normal clusters found per point: 1 plane,
        2..max_clusters feature, 0 no clear clusters (best mean silhouette below
        min_silhouette) or too few neighbours / usable triangles, max_clusters + 1 more
        than max_clusters (rough, no feature).
    timings: seconds per step ("neighbours", "gaussian_map", "kmeans", "total").
    """

    feature: np.ndarray
    clusters: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)


def gaussian_map_features(xyz: np.ndarray, *, cfg: FeaturesConfig,
                          rng: np.random.Generator | None = None,
                          progress: Callable[[int], None] | None = None) -> FeatureResult:
    """Feature points of a cloud by the Gaussian map of neighbour triangles + K-means.

    xyz: (N, 3) float, metres. cfg: FeaturesConfig (neighbours, max_clusters, plane_angle
    in degrees, min_silhouette, restarts, method, reference). rng: the K-means++ seeding;
    default np.random.default_rng(cfg.seed); the same rng state gives the same result.
    progress: told the number of points done after each chunk of them (a progress bar's
    `update`).

    Raises CloudFormatError when xyz is not (N, 3) or holds NaN / inf. Fewer than
    neighbours + 1 points: no features (every point clusters 0).
    """
    t_start = time.perf_counter()
    xyz = points_xyz(xyz, "gaussian_map_features: xyz")
    n = len(xyz)
    clusters = np.zeros(n, np.int8)
    timings = {"neighbours": 0.0, "gaussian_map": 0.0, "kmeans": 0.0}
    k = int(cfg.neighbours)
    if n < k + 1:
        timings["total"] = time.perf_counter() - t_start
        return FeatureResult(clusters >= 2, clusters, timings)
    if rng is None:
        rng = np.random.default_rng(cfg.seed)
    fast = cfg.method == "fast"
    dtype = np.float32 if fast else np.float64

    t0 = time.perf_counter()
    neighbours = _neighbours(xyz, k)
    timings["neighbours"] = time.perf_counter() - t0

    pair_m, pair_n = np.triu_indices(k, 1)
    n_pairs = len(pair_m)
    global_ref = None
    if cfg.reference == "highest":
        top = int(np.argmax(xyz[:, 2]))
        normal, _ = _pca(xyz[neighbours[top]][None] - xyz[top])
        global_ref = normal[0] * (1.0 if normal[0, 2] >= 0 else -1.0)  # up, for reading

    chunk = _chunk_size(n_pairs, cfg, fast)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        t0 = time.perf_counter()
        # (C, k, 3) neighbour offsets from their point: the triangles' two edges at p_i
        offsets = xyz[neighbours[start:stop]] - xyz[start:stop, None, :]
        ref, flatness = _pca(offsets)
        if global_ref is not None:
            ref = np.broadcast_to(global_ref, ref.shape)
        todo = np.ones(stop - start, bool)
        if fast:
            flat = flatness < FLAT_RATIO
            clusters[start:stop][flat] = PLANE
            todo = ~flat
        normals, valid = _gaussian_map(offsets[todo].astype(dtype), pair_m, pair_n,
                                       ref[todo].astype(dtype))
        codes = np.zeros(len(normals), np.int8)
        plane = _all_within(normals, valid, cfg.plane_angle)
        codes[plane] = PLANE
        enough = valid.sum(axis=1) >= 2 * (cfg.max_clusters + 1)
        cand = ~plane & enough
        t1 = time.perf_counter()
        timings["gaussian_map"] += t1 - t0
        if cand.any():
            codes[cand] = _count_clusters(normals[cand], valid[cand], cfg, rng)
        clusters[start:stop][todo] = codes
        timings["kmeans"] += time.perf_counter() - t1
        if progress is not None:
            progress(stop - start)

    timings["total"] = time.perf_counter() - t_start
    feature = (clusters >= 2) & (clusters <= cfg.max_clusters)
    return FeatureResult(feature, clusters, timings)


# --------------------------------------------------------------------------- steps


def _neighbours(xyz: np.ndarray, k: int) -> np.ndarray:
    """(N, k) int indices of the k nearest other points of each point.

    The point itself is dropped by index, not by position: with coincident points the
    query may list a twin before it."""
    n = len(xyz)
    _, idx = tree_query(cKDTree(xyz), xyz, k=k + 1, workers=-1)
    keep = idx != np.arange(n)[:, None]
    keep[keep.all(axis=1), -1] = False  # self not listed (k + 1 twins): drop the farthest
    return idx[keep].reshape(n, k)


def _pca(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal (C, 3) and flatness l3 / l2 (C,) of each neighbourhood (1 when l2 ~ 0).

    offsets: (C, k, 3) neighbours minus their point; the point itself (offset 0) belongs
    to the neighbourhood."""
    c, k, _ = offsets.shape
    mean = offsets.sum(axis=1) / (k + 1)
    centred = offsets - mean[:, None, :]
    cov = np.einsum("cki,ckj->cij", centred, centred) + mean[:, :, None] * mean[:, None, :]
    values = np.maximum(symmetric_eigenvalues3(cov), 0.0)  # descending
    # l3 / l2: ~0 on a plane, ~1 on a line (a wire is no plane, l3 / sum(l) is ~0 on both);
    # 1 where l2 is within the closed form's rounding of 0 (points on one line, or one
    # point): its arccos keeps ~8 digits of l1 where two eigenvalues meet
    spans = values[:, 1] > 1e-6 * values[:, 0]
    flatness = np.where(spans, values[:, 2] / np.where(spans, values[:, 1], 1.0), 1.0)
    return eigenvector3(cov, values[:, 2]), flatness


def _gaussian_map(offsets: np.ndarray, pair_m: np.ndarray, pair_n: np.ndarray,
                  ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit triangle normals (C, P, 3) of offsets.dtype and their validity (C, P) bool.

    offsets: (C, k, 3); pair_m, pair_n: (P,) neighbour indices of each triangle; ref:
    (C, 3), normals more than 90 deg from it are flipped. Invalid (degenerate) normals
    are zero vectors."""
    a = offsets[:, pair_m]
    b = offsets[:, pair_n]
    normals = np.cross(a, b)
    length = np.sqrt(np.einsum("cpi,cpi->cp", normals, normals))
    edges = np.sqrt(np.einsum("cpi,cpi->cp", a, a) * np.einsum("cpi,cpi->cp", b, b))
    # Measured and left out: also dropping triangles of small inradius (< 0.05 or 0.1 of
    # the mean neighbour distance) did not help the faithful plane test on a noisy box
    # (precision 0.40 -> 0.37, 0.37).
    valid = (length > np.sin(np.deg2rad(MIN_TRIANGLE_ANGLE)) * edges) & (length > 0)
    scale = np.where(valid, 1.0 / np.where(valid, length, 1.0), 0.0).astype(offsets.dtype)
    side = np.einsum("cpi,ci->cp", normals, ref)
    scale = np.where(side < 0, -scale, scale)
    return normals * scale[:, :, None], valid


def _all_within(normals: np.ndarray, valid: np.ndarray, angle_deg: float) -> np.ndarray:
    """(C,) bool: at least one valid normal and all within angle_deg of their mean."""
    mean = normals.sum(axis=1)  # invalid normals are zero
    length = np.sqrt((mean * mean).sum(axis=1))
    cos = np.einsum("cpi,ci->cp", normals, mean / np.where(length > 0, length, 1.0)[:, None])
    inside = (cos >= np.cos(np.deg2rad(angle_deg))) | ~valid
    return inside.all(axis=1) & valid.any(axis=1) & (length > 0)


def _chunk_size(n_pairs: int, cfg: FeaturesConfig, fast: bool) -> int:
    itemsize = 4 if fast else 8
    kmax = cfg.max_clusters + 1
    per_point = (6 * cfg.restarts * n_pairs * kmax + 12 * n_pairs
                 + 3 * n_pairs * n_pairs) * itemsize  # K-means, map, pairwise distances
    return int(max(16, min(8192, CHUNK_BYTES // per_point)))


def _manhattan(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """L1 distances (..., P, K) of points x (..., P, 3) to centres (..., K, 3)."""
    out = np.abs(x[..., :, None, 0] - centres[..., None, :, 0])
    out += np.abs(x[..., :, None, 1] - centres[..., None, :, 1])
    out += np.abs(x[..., :, None, 2] - centres[..., None, :, 2])
    return out


def _count_clusters(normals: np.ndarray, valid: np.ndarray, cfg: FeaturesConfig,
                    rng: np.random.Generator) -> np.ndarray:
    """(C,) int8 cluster code of each point from its normals (C, P, 3), valid (C, P)."""
    c = len(normals)
    ks = range(2, cfg.max_clusters + 2)
    scores = np.full((c, len(ks)), -np.inf)
    pairwise = _manhattan(normals, normals)  # (C, P, P)
    kept = np.zeros((c, len(ks)), np.int8)
    n_valid = valid.sum(axis=1)
    for j, kc in enumerate(ks):
        labels, centres = _kmeans(normals, valid, kc, cfg.restarts, rng)
        scores[:, j] = _silhouette(pairwise, valid, labels, kc)
        size = (labels[..., None] == np.arange(kc)).sum(axis=1)
        kept[:, j] = (size >= MIN_CLUSTER_SHARE * n_valid[:, None]).sum(axis=1)
    best = scores.argmax(axis=1)
    codes = kept[np.arange(c), best]
    codes[scores[np.arange(c), best] < cfg.min_silhouette] = NO_CLUSTERS
    return codes


def _kmeans(x: np.ndarray, valid: np.ndarray, k: int, restarts: int,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """K-means with the Manhattan distance, batched: the best of `restarts` runs each.

    x: (C, P, 3) normals, valid: (C, P) bool (at least k valid per row). Seeding is
    K-means++ (probability of the squared L1 distance to the nearest chosen centre);
    assignment by L1 distance, centres the means (the paper's eq. 3 and its update), until
    no label changes. Returns labels (C, P) int (-1 for invalid normals) and centres
    (C, k, 3) of the run of the lowest total L1 distance."""
    c, p, _ = x.shape
    w = valid.astype(x.dtype)
    rows = np.arange(c)[:, None]
    # K-means++ seeding for all (point, restart) at once: (C, R, k, 3) centres
    centres = np.empty((c, restarts, k, 3), x.dtype)
    weight = np.broadcast_to(w[:, None, :], (c, restarts, p))
    nearest = None
    for j in range(k):
        pick = _draw(weight if nearest is None else weight * nearest * nearest,
                     weight, rng)
        centres[:, :, j] = x[rows, pick]
        d = _manhattan(x[:, None], centres[:, :, j:j + 1])[..., 0]  # (C, R, P)
        nearest = d if nearest is None else np.minimum(nearest, d)

    # Lloyd iterations on the runs still changing only: (B, P, 3) with B = C R, the runs
    # leave the active set when no label changes (most converge in 3-6 iterations, a few
    # take 20+; iterating all until the last converged cost 2.5 x more on a noisy box).
    xb = np.repeat(x, restarts, axis=0)  # (B, P, 3)
    vb = np.repeat(valid, restarts, axis=0)
    cb = centres.reshape(c * restarts, k, 3)
    labels = np.full((c * restarts, p), -1, np.intp)
    active = np.arange(c * restarts)
    clusters = np.arange(k)
    for _ in range(MAX_LLOYD):
        xa, ca = xb[active], cb[active]
        new = _manhattan(xa, ca).argmin(axis=-1)  # (A, P)
        changed = (new != labels[active]).any(axis=1)
        active, new, xa, ca = active[changed], new[changed], xa[changed], ca[changed]
        if not len(active):
            break
        labels[active] = new
        member = (new[..., None] == clusters) & vb[active][..., None]  # (A, P, k)
        count = member.sum(axis=1)  # (A, k)
        sums = np.matmul(member.transpose(0, 2, 1).astype(x.dtype), xa)  # (A, k, 3)
        # an emptied cluster keeps its centre (it may win points back)
        cb[active] = np.where(count[..., None] > 0,
                              sums / np.maximum(count, 1)[..., None].astype(x.dtype), ca)
    dist = _manhattan(xb, cb)  # (B, P, k)
    cost = (dist.min(axis=-1) * vb).sum(axis=-1).reshape(c, restarts)
    best = np.arange(c) * restarts + cost.argmin(axis=1)
    labels = dist[best].argmin(axis=-1)
    labels[~valid] = -1
    return labels, cb[best]


def _draw(weight: np.ndarray, fallback: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One index per row of weight (..., P), drawn with probability proportional to it;
    rows whose weights are all zero (every sample on a chosen centre) draw by fallback
    (..., P), the validity weights."""
    weight = np.where(weight.sum(axis=-1, keepdims=True) > 0, weight, fallback)
    cdf = np.cumsum(weight, axis=-1)
    u = rng.random(weight.shape[:-1] + (1,)) * cdf[..., -1:]
    pick = (cdf <= u).sum(axis=-1)
    # rounding can push u to the total: the last sample of positive weight then
    last = weight.shape[-1] - 1 - np.argmax(weight[..., ::-1] > 0, axis=-1)
    return np.minimum(pick, last)


def _silhouette(pairwise: np.ndarray, valid: np.ndarray, labels: np.ndarray,
                k: int) -> np.ndarray:
    """(C,) mean silhouette of labels (C, P) from the pairwise L1 distances (C, P, P).

    s = (b - a) / max(a, b), a the mean distance to the other members of the own cluster,
    b the least mean distance to another cluster's members (paper eq. 4); 0 for a member
    alone in its cluster (the usual convention). -inf when fewer than 2 clusters hold
    points (the silhouette is undefined)."""
    member = (labels[..., None] == np.arange(k)).astype(pairwise.dtype)  # (C, P, k), 0 if invalid
    count = member.sum(axis=1)  # (C, k)
    sums = np.matmul(pairwise, member)  # (C, P, k): distance sum to each cluster
    own = np.clip(labels, 0, None)[..., None]
    own_count = np.take_along_axis(count, own[..., 0], axis=1)  # (C, P)
    a = np.take_along_axis(sums, own, axis=2)[..., 0] / np.maximum(own_count - 1, 1)
    mean_to = sums / np.maximum(count, 1)[:, None, :]
    mean_to = np.where((member > 0) | (count[:, None, :] == 0), np.inf, mean_to)
    b = mean_to.min(axis=2)
    return _mean_silhouette(a, b, own_count > 1, valid, count)


def _mean_silhouette(a: np.ndarray, b: np.ndarray, shared: np.ndarray, valid: np.ndarray,
                     count: np.ndarray) -> np.ndarray:
    top = np.maximum(a, b)
    s = np.where(shared & np.isfinite(b) & (top > 0),
                 (b - a) / np.where(top > 0, top, 1.0), 0.0)
    s = np.where(valid, s, 0.0)
    mean = s.sum(axis=1) / np.maximum(valid.sum(axis=1), 1)
    return np.where((count > 0).sum(axis=1) >= 2, mean, -np.inf)
