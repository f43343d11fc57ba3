"""Scattered-data interpolators for the DEM and the paper's thinning protocol.

One entry, :func:`interpolate`, with five methods:

- ``tin``: Delaunay triangulation, linear inside each triangle, NaN outside the hull.
- ``idw``: inverse distance weighting of the nearest samples.
- ``kriging``: ordinary kriging with a variogram fitted to the samples (nugget by
  cross-validation, see :func:`choose_nugget`), on LOCAL neighbourhoods. Written in the
  dual form, estimate(x) = sum_i a_i gamma(|x - x_i|) + b
  with [Gamma 1; 1' 0][a; b] = [z; 0], which is algebraically the same as solving for the
  kriging weights but needs one solve per neighbourhood instead of one per query; queries
  in the same block of one sample spacing share a neighbourhood (a grid denser than the
  data solves about one system per sample). The systems are solved stacked,
  (U, k+1, k+1), with one np.linalg.solve call per chunk.
- ``rbf``: local radial basis functions with a linear polynomial, the same dual machinery.
- ``rbfnn``: the paper's RBF network (like MATLAB newrb): Gaussian units added one at a
  time at the worst-fitted sample until the training MSE reaches the goal.

Degenerate input never raises from Qhull or LAPACK: coincident samples are merged (mean z),
fewer than 3 samples or collinear samples give NaN for ``tin``; the other methods still
answer (a constant or a line's extension), see :func:`degeneracy` for the reason text.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Callable, ContextManager

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import least_squares
from scipy.spatial import ConvexHull, Delaunay, QhullError, cKDTree

from lidar_obstacles.core.arrays import points_xyz, thread_pools, tree_query
from lidar_obstacles.config import KrigingConfig, RbfConfig, RbfnnConfig
from lidar_obstacles.errors import CloudFormatError

METHODS = ("tin", "idw", "kriging", "rbf", "rbfnn")
_CHUNK = 4096  # local systems solved per stacked call: bounds memory to a few MB
# The seed of the fits' random draws (the variogram's sample pairs, the nugget's held-out
# samples, the RBF network's training points) when the caller gives none: fixed, so the
# same samples give the same surface in every run. None draws from fresh entropy instead.
SAMPLING_SEED = 0


# --------------------------------------------------------------------------- input


def one_blas_thread() -> ContextManager:
    """Context in which BLAS/LAPACK run in one thread.

    SciPy's Delaunay computes its barycentric transforms with one tiny LAPACK call per
    triangle; with OpenBLAS's 2 threads on a machine whose cores are busy each call waits
    for the other thread, and 8 000 triangles took 0.2-0.6 s instead of 0.016 s. The
    cached controller makes entering the context cost ~5 us. Nothing is set when every
    BLAS is on one thread already (the nodes, `replay`'s workers): setting it, even to 1,
    in a forked child starts OpenBLAS's threads, which spin ~0.1 s each.
    """
    blas = thread_pools().select(user_api="blas")
    if all(lib.num_threads == 1 for lib in blas.lib_controllers):
        return contextlib.nullcontext()
    return blas.limit(limits=1)


def neighbour_residual(xyz: np.ndarray, indptr: np.ndarray, neighbours: np.ndarray
                       ) -> np.ndarray:
    """(N,) float64 |z - the plane of its neighbours at the point| (m) of (N, 3) points,
    their neighbours given as a Delaunay's `vertex_neighbor_vertices` (indptr (N + 1,),
    neighbours): the least-squares plane through each point's neighbours, weighted by
    1 / distance, met at the point. 0 on any plane, tilted or not (the inverse-distance
    mean of the neighbours it was before is off on a slope wherever they are unevenly
    spaced: a 30 % slope at 2 m spacing gave 0.05 m at the median and 0.9 m on the
    hull); where the neighbours fix no plane (in a line), their inverse-distance mean;
    0 for a point with none."""
    n = len(xyz)
    owner = np.repeat(np.arange(n), np.diff(indptr))
    dx, dy, dz = (xyz[neighbours] - xyz[owner]).T  # the neighbours seen from the point
    w = 1.0 / np.maximum(np.hypot(dx, dy), 1e-9)

    def total(v: np.ndarray) -> np.ndarray:
        return np.bincount(owner, weights=w * v, minlength=n)

    one = np.ones_like(w)
    sw, sx, sy, sz = total(one), total(dx), total(dy), total(dz)
    sxx, sxy, syy, sxz, syz = total(dx * dx), total(dx * dy), total(dy * dy), \
        total(dx * dz), total(dy * dz)
    # normal equations of dz = a + b dx + c dy, one symmetric 3 x 3 system a point, solved
    # for a (the plane's height over the point's own) by Cramer's rule, all at once (40 ->
    # 23 ms for 50 000 points against a batched np.linalg.solve)
    minor_xy = sxx * syy - sxy * sxy
    det = sw * minor_xy - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
    det_a = sz * minor_xy - sx * (sxz * syy - sxy * syz) + sy * (sxz * sxy - sxx * syz)
    # (Hadamard: the determinant of such a matrix is at most its diagonal's product; far
    # below it, the neighbours lie in a line)
    plane = det > 1e-9 * sw * sxx * syy
    out = np.zeros(n)
    out[plane] = np.abs(det_a[plane] / det[plane])
    line = ~plane & (sw > 0)
    out[line] = np.abs(sz[line] / sw[line])
    return out


def _check(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """xy (N, 2) m, z (N,) m and query_xy (M, 2) m as float64, or CloudFormatError for
    another shape. Not searched for NaN: the DEM hands only its finite ground."""
    xy = points_xyz(xy, "interpolate: xy", columns=2, nonfinite="keep")
    z = np.asarray(z, dtype=np.float64)
    if z.shape != (len(xy),):
        raise CloudFormatError(f"interpolate: expected z of shape ({len(xy)},) as xy "
                               f"{xy.shape}, got {z.shape}")
    q = points_xyz(query_xy, "interpolate: query_xy", columns=2, nonfinite="keep")
    return xy, z, q


def merge_coincident(xy: np.ndarray, z: np.ndarray, *, quantum: float = 1e-6,
                     extra: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Drop non-finite samples and merge samples closer than ``quantum`` (m) in XY.

    Returns (xy (U, 2), z (U,)) — plus extra (U,) when given — with means per merged
    group. Coincident samples make every interpolation system singular.
    """
    ok = np.all(np.isfinite(xy), axis=1) & np.isfinite(z)
    if extra is not None:
        ok &= np.isfinite(extra)
    xy, z = xy[ok], z[ok]
    keys = np.round(xy / quantum).astype(np.int64)
    _, first, inverse, counts = np.unique(keys, axis=0, return_index=True,
                                          return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if len(first) == len(xy):
        return (xy, z) if extra is None else (xy, z, extra[ok])
    mean = [np.bincount(inverse, weights=v) / counts for v in (xy[:, 0], xy[:, 1], z)]
    out: tuple[np.ndarray, ...] = (np.column_stack(mean[:2]), mean[2])
    if extra is not None:
        out += (np.bincount(inverse, weights=extra[ok]) / counts,)
    return out


def degeneracy(xy: np.ndarray) -> str:
    """Why samples (N, 2) cannot span a surface ("" when they can): too few or collinear."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 3:
        return f"only {len(xy)} distinct sample(s); a surface needs 3"
    centred = xy - xy.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] == 0.0 or s[1] <= 1e-9 * s[0]:
        return "all samples are collinear (or coincident) in XY"
    return ""


# --------------------------------------------------------------------------- tin / idw


def tin(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray) -> np.ndarray:
    """Linear interpolation on the Delaunay TIN; NaN outside the hull or when degenerate.

    xy: (N, 2) float64 sample positions, metres (coincident ones merged first, see
    :func:`merge_coincident`). z: (N,) float64 sample heights, metres. query_xy: (M, 2)
    float64, metres. Returns (M,) float64 heights, metres.
    """
    out = np.full(len(query_xy), np.nan)
    if degeneracy(xy) or len(query_xy) == 0:
        return out
    # Centred coordinates: scipy's barycentric transforms of a survey in UTM/RD metres
    # (1e5-1e6 m offsets) took 12 s for 20 000 triangles instead of 0.02 s.
    shift = xy.mean(axis=0)
    xy, query_xy = xy - shift, query_xy - shift
    try:
        tri = Delaunay(xy)
    except QhullError:  # nearly collinear sets that passed the SVD test
        return out
    # Qhull's point location walks the triangulation and falls back to a brute-force
    # search over every triangle when the walk leaves the hull, so queries outside the
    # hull cost O(triangles) each (seconds for a DEM); they are screened out first.
    eq = ConvexHull(xy).equations
    tol = 1e-9 * float(np.abs(xy).max() + 1.0)
    candidate = np.ones(len(query_xy), dtype=bool)
    for lo in range(0, len(query_xy), _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        candidate[sl] = np.all(query_xy[sl] @ eq[:, :2].T + eq[:, 2] <= tol, axis=1)
    # Qhull walks from the previous query's triangle and falls back to a search over all
    # triangles when the walk fails, so scattered queries (the protocol's random check
    # points) cost 0.5-5 s for 16 000 queries and 4 000 samples where the same queries in
    # serpentine row order cost 2 ms: visit them along rows one sample spacing high.
    cand = np.flatnonzero(candidate)
    spacing = float(np.sqrt(max(np.prod(np.ptp(xy, axis=0)), 1e-18) / len(xy)))
    row = np.floor(query_xy[cand, 1] / spacing).astype(np.int64)
    along = np.where(row % 2 == 0, query_xy[cand, 0], -query_xy[cand, 0])
    cand = cand[np.lexsort((along, row))]
    simplex = np.full(len(query_xy), -1)
    with one_blas_thread():  # find_simplex computes the transforms on first use
        simplex[cand] = tri.find_simplex(query_xy[cand])
    inside = simplex >= 0
    s = simplex[inside]
    trans = tri.transform[s]
    bary2 = np.einsum("mij,mj->mi", trans[:, :2], query_xy[inside] - trans[:, 2])
    bary = np.column_stack([bary2, 1.0 - bary2.sum(axis=1)])
    out[inside] = np.einsum("mi,mi->m", bary, z[tri.simplices[s]])
    return out


def idw(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, *, neighbours: int = 8,
        power: float = 2.0) -> np.ndarray:
    """Inverse distance weighting of the ``neighbours`` nearest samples (exact at samples).

    xy: (N, 2) float64 sample positions, metres. z: (N,) float64 sample heights, metres.
    query_xy: (M, 2) float64, metres. power: the exponent p of the weights 1 / d^p (d in
    metres). Returns (M,) float64 heights, metres; all NaN when there are no samples.
    """
    if len(xy) == 0:
        return np.full(len(query_xy), np.nan)
    k = min(neighbours, len(xy))
    d, idx = tree_query(cKDTree(xy), query_xy, k=k, workers=-1)
    d, idx = d.reshape(len(query_xy), k), idx.reshape(len(query_xy), k)
    w = 1.0 / np.maximum(d, 1e-12) ** power
    exact = d[:, 0] <= 1e-12
    out = np.einsum("mk,mk->m", w, z[idx]) / w.sum(axis=1)
    out[exact] = z[idx[exact, 0]]
    return out


# --------------------------------------------------------------------------- variogram


def _variogram_model(name: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """gamma(h; nugget, partial sill, range) for h > 0 (gamma(0) = 0 is set separately)."""
    def spherical(h, p):
        r = np.minimum(h / p[2], 1.0)
        return p[0] + p[1] * (1.5 * r - 0.5 * r ** 3)

    def exponential(h, p):
        return p[0] + p[1] * (1.0 - np.exp(-3.0 * h / p[2]))

    def gaussian(h, p):
        return p[0] + p[1] * (1.0 - np.exp(-(h / (4.0 / 7.0 * p[2])) ** 2))

    def linear(h, p):
        return p[0] + p[1] * h / p[2]

    return {"spherical": spherical, "exponential": exponential, "gaussian": gaussian,
            "linear": linear}[name]


@dataclass(frozen=True)
class Variogram:
    """A fitted variogram: gamma(h) = nugget + partial_sill * model(h / range_), m^2."""

    model: str
    nugget: float
    partial_sill: float
    range_: float

    def __call__(self, h: np.ndarray) -> np.ndarray:
        """gamma at lags h (any shape), metres -> the same shape, m^2; 0 at h = 0."""
        g = _variogram_model(self.model)(h, np.array([self.nugget, self.partial_sill,
                                                      self.range_]))
        return np.where(h > 0, g, 0.0)


def fit_variogram(xy: np.ndarray, z: np.ndarray, *, model: str, neighbours: int,
                  rng: np.random.Generator | int | None = SAMPLING_SEED) -> Variogram:
    """Fit a variogram to the samples' semivariances at the lags local kriging uses.

    Pairs: each of up to 3000 random samples with its 2*neighbours nearest (the short
    lags local kriging sees) plus 20000 random pairs (the sill). Lags are binned by
    quantiles so every bin holds as many pairs; the model is fitted by least squares with
    short lags weighted up. A flat or tiny set gives a pure linear variogram.

    xy: (N, 2) float64 sample positions, metres. z: (N,) float64 sample heights, metres.
    neighbours: the neighbourhood size of local kriging (count). rng: seed or generator of
    the random pairs. Returns the Variogram: nugget and partial_sill in m^2 (semivariance
    of z), range_ in metres.
    """
    gen = np.random.default_rng(rng)
    n = len(xy)
    if n < 3 or np.ptp(z) == 0:
        return Variogram(model="linear", nugget=0.0, partial_sill=1.0, range_=1.0)
    sub = gen.choice(n, min(n, 3000), replace=False)
    k = min(2 * neighbours + 1, n)
    _, idx = cKDTree(xy).query(xy[sub], k=k)
    a = np.concatenate([np.repeat(sub, k - 1), gen.integers(n, size=20000)])
    b = np.concatenate([idx[:, 1:].ravel(), gen.integers(n, size=20000)])
    h = np.hypot(*(xy[a] - xy[b]).T)
    g = 0.5 * (z[a] - z[b]) ** 2
    ok = h > 0
    h, g = h[ok], g[ok]
    edges = np.unique(np.quantile(h, np.linspace(0.0, 1.0, 31)))
    bins = np.clip(np.searchsorted(edges, h, side="right") - 1, 0, len(edges) - 2)
    cnt = np.bincount(bins, minlength=len(edges) - 1)
    use = cnt > 0
    lag = (np.bincount(bins, weights=h, minlength=len(edges) - 1)[use] / cnt[use])
    semi = (np.bincount(bins, weights=g, minlength=len(edges) - 1)[use] / cnt[use])
    fn = _variogram_model(model)
    top = max(float(semi.max()), 1e-12)
    p0 = np.array([0.0, top, float(np.median(lag)) if model != "linear" else float(lag.max())])
    weight = 1.0 / np.sqrt(lag / lag.max())

    def residual(p):
        return weight * (fn(lag, p) - semi) / top

    fit = least_squares(residual, p0, bounds=([0.0, 0.0, 1e-3 * lag.min() + 1e-9],
                                              [top, 10.0 * top, 10.0 * lag.max()]))
    nug, psill, rng_ = (float(v) for v in fit.x)
    return Variogram(model=model, nugget=nug, partial_sill=max(psill, 1e-12 * top),
                     range_=rng_)


# --------------------------------------------------------------------------- local dual


_MAX_BLOCK_LEVEL = 4  # blocks at most 16 spacings wide


@dataclass(frozen=True)
class _Blocks:
    """Local neighbourhoods of M queries: block (M,) int64 block of each query; centre
    (B, 2) metres, the mean of each block's queries; sets (B, k) int64 its k nearest
    samples; scale: the median distance to the k-th of them (metres)."""

    block: np.ndarray
    centre: np.ndarray
    sets: np.ndarray
    scale: float


def _blocks(xy: np.ndarray, query_xy: np.ndarray, k: int) -> _Blocks:
    """Group queries (M, 2) in square blocks and find the k samples of xy (N, 2) nearest
    to each block's centre. A block is one mean sample spacing wide near the samples and
    wider away from them: 2 spacings from 4 spacings away from the nearest sample, 4 from
    8 and so on, always less than half that distance, so every query stays well inside
    its block's neighbourhood while the queries there all have nearly the same k nearest
    samples. A rolling DEM's refill is mostly such cells (the margin of fill_distance
    around the data): on the simulated `mixed` flight each 1 Hz kriging refill took ~75 ms
    and now ~35 ms, the margin's cells moving by 0.06-0.12 m on average where they err by
    2.0-2.7 m against the true terrain either way; cells within 4 m of the data are not
    touched."""
    k = min(k, len(xy))
    lo_xy = xy.min(axis=0)
    extent = np.maximum(xy.max(axis=0) - lo_xy, 1e-9)
    spacing = float(np.sqrt(extent[0] * extent[1] / len(xy))) or float(extent.max() / len(xy))
    tree = cKDTree(xy)
    nearest, _ = tree_query(tree, query_xy, k=1, workers=-1)
    level = np.floor(np.log2(np.maximum(nearest / (2.0 * spacing), 1.0)))
    level = np.minimum(np.nan_to_num(level), _MAX_BLOCK_LEVEL)
    width = spacing * 2.0 ** level
    cells = np.column_stack([level, np.floor((query_xy - lo_xy) / width[:, None])])
    _, block, counts = np.unique(cells.astype(np.int64), axis=0, return_inverse=True,
                                 return_counts=True)
    block = block.ravel()
    centre = np.column_stack([np.bincount(block, weights=query_xy[:, i]) / counts
                              for i in range(2)])
    dist, sets = tree_query(tree, centre, k=k, workers=-1)
    dist, sets = dist.reshape(len(centre), k), sets.reshape(len(centre), k)
    return _Blocks(block, centre, sets, float(np.median(dist[:, -1])) or 1.0)


def _local_dual(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, *, k: int,
                kernel: Callable[[np.ndarray, float], np.ndarray], linear_drift: bool,
                diagonal: float, blocks: _Blocks | None = None) -> np.ndarray:
    """Evaluate s(x) = sum_i a_i kernel(|x - x_i|) + polynomial over local neighbourhoods.

    Queries are grouped in square blocks one mean sample spacing wide (wider far from
    the samples); a block's neighbourhood is the k samples nearest to its queries' mean
    (:func:`_blocks`; pass
    ``blocks`` to reuse them across kernels), so a grid denser than the data solves about
    one system per sample instead of one per cell, and every query stays well inside its
    neighbourhood (radius ~ sqrt(k/pi) spacings). Each block solves the saddle system
    [K + diagonal*I, P; P', 0][a; c] = [z; 0] with P = [1] (constant) or [1, x, y]
    (linear drift), stacked _CHUNK at a time. Coordinates are centred per block and
    scaled by ``scale`` (the median distance to the k-th neighbour) for conditioning; the
    kernel is called as kernel(squared distance / scale^2, scale). A singular stack
    (collinear samples with a linear drift) falls back to the pseudo-inverse.
    """
    m = len(query_xy)
    nb = blocks if blocks is not None else _blocks(xy, query_xy, k)
    block, centre, sets, scale = nb.block, nb.centre, nb.sets, nb.scale
    k = sets.shape[1]
    npoly = 3 if linear_drift else 1
    size = k + npoly
    coef = np.empty((len(sets), size))
    diag = np.arange(k)
    for lo in range(0, len(sets), _CHUNK):
        s = sets[lo:lo + _CHUNK]
        local = (xy[s] - centre[lo:lo + _CHUNK, None, :]) / scale
        sq = np.einsum("uki,uki->uk", local, local)
        r2 = sq[:, :, None] + sq[:, None, :] - 2.0 * np.einsum("uki,uli->ukl", local, local)
        a = np.zeros((len(s), size, size))
        a[:, :k, :k] = kernel(np.maximum(r2, 0.0), scale)
        a[:, diag, diag] += diagonal
        a[:, :k, k] = a[:, k, :k] = 1.0
        if linear_drift:
            a[:, :k, k + 1:] = local
            a[:, k + 1:, :k] = local.transpose(0, 2, 1)
        rhs = np.zeros((len(s), size, 1))
        rhs[:, :k, 0] = z[s]
        try:
            with one_blas_thread():  # thousands of tiny solves: threads only wait
                coef[lo:lo + len(s)] = np.linalg.solve(a, rhs)[:, :, 0]
        except np.linalg.LinAlgError:
            coef[lo:lo + len(s)] = (np.linalg.pinv(a) @ rhs)[:, :, 0]
    out = np.empty(m)
    for lo in range(0, m, _CHUNK):
        q = slice(lo, lo + _CHUNK)
        u = block[q]
        d2 = np.sum((xy[sets[u]] - query_xy[q, None, :]) ** 2, axis=2) / scale ** 2
        val = np.einsum("mk,mk->m", coef[u, :k], kernel(d2, scale)) + coef[u, k]
        if linear_drift:
            val += np.einsum("mi,mi->m", coef[u, k + 1:], (query_xy[q] - centre[u]) / scale)
        out[q] = val
    return out


# Nugget candidates, as shares of the structured variogram at one sample spacing: from
# an exact interpolator (0) to one that mostly averages its neighbours (3).
_NUGGET_SHARES = (0.0, 0.1, 0.3, 1.0, 3.0)


def _ordinary(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, vg: Variogram,
              k: int, blocks: _Blocks | None = None) -> np.ndarray:
    """Local ordinary kriging (dual form) with variogram ``vg`` on k neighbours."""
    # A tiny negative diagonal (= a tiny positive covariance nugget) keeps Gaussian
    # variograms, whose matrices are nearly singular, solvable.
    return _local_dual(xy, z, query_xy, k=k, kernel=lambda r2, scale: vg(np.sqrt(r2) * scale),
                       linear_drift=False, diagonal=-1e-10 * (vg.nugget + vg.partial_sill),
                       blocks=blocks)


def choose_nugget(xy: np.ndarray, z: np.ndarray, vg: Variogram, *, neighbours: int,
                  rng: np.random.Generator | int | None = SAMPLING_SEED) -> Variogram:
    """The variogram ``vg`` with its nugget chosen by hold-out cross-validation.

    The binned fit's nugget is poor for LOCAL kriging: it comes from lags out to the sill
    (0.107 m^2 on ISPRS samp41, a site with 7 m walls, which smoothed across them) while
    only the first few sample spacings matter. So min(1000, N/10) random samples are held
    out and predicted from the others with nugget = share * gamma_structured(spacing) for
    each share in (0, 0.1, 0.3, 1, 3); the smallest nugget whose mean squared error is
    within one paired standard error of the best is kept (noise in a few breakline points
    must not buy a smoother surface). Measured on the 36 protocol cases (bench_dem.py):
    noisy dense AHN ground takes 1-3 (RMSE 3-7 % below the fitted nugget's), the sparser
    ISPRS sites 0-0.3. Fewer than 300 samples: ``vg`` is returned unchanged.
    xy: (N, 2) metres; z: (N,) metres.
    """
    n = len(xy)
    n_out = min(1000, n // 10)
    structured = Variogram(vg.model, 0.0, vg.partial_sill, vg.range_)
    extent = np.ptp(xy, axis=0)
    spacing = float(np.sqrt(extent[0] * extent[1] / n)) if n else 0.0
    unit = float(structured(np.array([spacing]))[0]) if spacing > 0 else 0.0
    if n_out < 30 or not unit > 0:
        return vg
    gen = np.random.default_rng(rng)
    out = gen.choice(n, n_out, replace=False)
    inside = np.ones(n, dtype=bool)
    inside[out] = False
    blocks = _blocks(xy[inside], xy[out], neighbours)  # one neighbour search for all
    sq = np.array([(_ordinary(xy[inside], z[inside], xy[out],
                              Variogram(vg.model, share * unit, vg.partial_sill, vg.range_),
                              neighbours, blocks) - z[out]) ** 2 for share in _NUGGET_SHARES])
    diff = sq - sq[int(np.argmin(sq.mean(axis=1)))]
    se = diff.std(axis=1, ddof=1) / np.sqrt(n_out)
    share = _NUGGET_SHARES[int(np.argmax(diff.mean(axis=1) <= se))]
    return Variogram(vg.model, share * unit, vg.partial_sill, vg.range_)


def kriging_variogram(xy: np.ndarray, z: np.ndarray, *, cfg: KrigingConfig,
                      rng: np.random.Generator | int | None = SAMPLING_SEED) -> Variogram:
    """The variogram :func:`kriging` uses: shape, sill and range fitted to binned
    semivariances (:func:`fit_variogram`), nugget by cross-validation
    (:func:`choose_nugget`). xy: (N, 2) metres; z: (N,) metres."""
    gen = np.random.default_rng(rng)
    vg = fit_variogram(xy, z, model=cfg.variogram, neighbours=cfg.neighbours, rng=gen)
    return choose_nugget(xy, z, vg, neighbours=cfg.neighbours, rng=gen)


def kriging(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, *, cfg: KrigingConfig,
            rng: np.random.Generator | int | None = SAMPLING_SEED,
            variogram: Variogram | None = None) -> np.ndarray:
    """Ordinary kriging on the ``cfg.neighbours`` nearest samples of each query, with
    ``variogram`` (default: :func:`kriging_variogram` of the samples). xy: (N, 2) metres;
    z: (N,) metres; query_xy: (M, 2) metres -> (M,) metres."""
    vg = variogram if variogram is not None else kriging_variogram(xy, z, cfg=cfg, rng=rng)
    return _ordinary(xy, z, query_xy, vg, cfg.neighbours)


def _rbf_kernel(name: str, k: int) -> Callable[[np.ndarray], np.ndarray]:
    """Kernels of the SQUARED distance r2 (in units of the neighbourhood radius), signs as
    in scipy's RBFInterpolator (conditionally positive definite). r^2 log r = r2 log(r2)/2.
    The shape parameter of gaussian and multiquadric makes their width about one sample
    spacing (radius / sqrt(k/4)); wider Gaussians are numerically singular."""
    eps2 = k / 4.0

    def tps(r2):
        return 0.5 * r2 * np.log(np.maximum(r2, 1e-300))

    return {"thin_plate_spline": tps, "linear": lambda r2: -np.sqrt(r2),
            "cubic": lambda r2: r2 * np.sqrt(r2),
            "multiquadric": lambda r2: -np.sqrt(1.0 + eps2 * r2),
            "gaussian": lambda r2: np.exp(-eps2 * r2)}[name]


def rbf(xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, *, cfg: RbfConfig) -> np.ndarray:
    """Local RBF interpolation with a linear polynomial (a constant when the samples
    are collinear, where a plane is undetermined) on the ``cfg.neighbours`` nearest
    samples; exact for planes.

    xy: (N, 2) float64 sample positions, metres (coincident ones merged first). z: (N,)
    float64 sample heights, metres. query_xy: (M, 2) float64, metres. cfg: kernel, number
    of neighbours, smoothing (added to the kernel matrix diagonal, distances scaled by
    the neighbourhood radius). Returns (M,) float64 heights, metres.
    """
    fn = _rbf_kernel(cfg.kernel, min(cfg.neighbours, len(xy)))
    return _local_dual(xy, z, query_xy, k=cfg.neighbours, kernel=lambda r2, _scale: fn(r2),
                       linear_drift=not degeneracy(xy), diagonal=cfg.smoothing)


# --------------------------------------------------------------------------- rbf network


@dataclass(frozen=True)
class RbfNetwork:
    """A trained Gaussian RBF network z = sum_j w_j exp(-(b |u - c_j|)^2) + w_0.

    centres: (J, D) in standardised inputs; weights: (J,); bias: float; b: 0.8326/spread
    (a unit answers 0.5 at distance ``spread``, as MATLAB's radbas/newrb); mean, std:
    (D,) of the training inputs; mse: training mean squared error (m^2).
    """

    centres: np.ndarray
    weights: np.ndarray
    bias: float
    b: float
    mean: np.ndarray
    std: np.ndarray
    mse: float

    @property
    def neurons(self) -> int:
        """J, the number of hidden units."""
        return len(self.centres)

    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """inputs: (M, D) raw (unstandardised) inputs -> (M,) float64 predictions."""
        u = (np.asarray(inputs, dtype=np.float64) - self.mean) / self.std
        out = np.full(len(u), self.bias)
        for lo in range(0, len(u), _CHUNK):
            sl = slice(lo, lo + _CHUNK)
            d2 = np.sum((u[sl, None, :] - self.centres[None]) ** 2, axis=2)
            out[sl] += np.exp(-(self.b ** 2) * d2) @ self.weights
        return out


def train_rbfnn(inputs: np.ndarray, z: np.ndarray, *, goal: float, spread: float,
                max_neurons: int) -> RbfNetwork:
    """Train the paper's RBF network like MATLAB newrb.

    inputs: (N, D) raw features (X, Y[, intensity]); they are standardised inside. One
    Gaussian unit at a time is centred on the training sample with the largest residual;
    the output weights are the least-squares fit of all units plus a bias, kept up to date
    by Gram-Schmidt (orthogonal least squares), so each step costs O(N J). Stops when the
    training MSE <= goal (m^2), after ``max_neurons`` units, or after 4 * max_neurons
    candidates (units the others already span are skipped).
    """
    x = np.asarray(inputs, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    mean = x.mean(axis=0)
    std = x.std(axis=0, ddof=1) if len(x) > 1 else np.ones(x.shape[1])
    std = np.where(std > 0, std, 1.0)
    u = (x - mean) / std
    n = len(u)
    b = float(np.sqrt(np.log(2.0)) / spread)
    qt = np.zeros((max_neurons + 1, n))  # orthonormal basis, one row per unit (contiguous)
    r_mat = np.zeros((max_neurons + 1, max_neurons + 1))
    qt[0] = 1.0 / np.sqrt(n)
    r_mat[0, 0] = np.sqrt(n)
    resid = z - z.mean()
    proj = [float(qt[0] @ z)]
    centres: list[int] = []
    usable = np.ones(n, dtype=bool)
    j = 1
    # A candidate whose unit the others already span is skipped; with wide units most
    # are, so attempts are bounded too (4 per unit) instead of scanning every sample.
    attempts = 4 * max_neurons
    while j <= max_neurons and attempts > 0 and np.mean(resid ** 2) > goal and usable.any():
        attempts -= 1
        i = int(np.argmax(np.where(usable, np.abs(resid), -1.0)))
        usable[i] = False
        phi = np.exp(-(b ** 2) * np.sum((u - u[i]) ** 2, axis=1))
        coeffs = qt[:j] @ phi
        v = phi - coeffs @ qt[:j]
        again = qt[:j] @ v  # second Gram-Schmidt pass: orthogonality to machine precision
        v -= again @ qt[:j]
        norm = float(np.linalg.norm(v))
        if norm <= 1e-8 * float(np.linalg.norm(phi)):
            continue
        qt[j] = v / norm
        r_mat[:j, j] = coeffs + again
        r_mat[j, j] = norm
        proj.append(float(qt[j] @ resid))
        resid = resid - proj[-1] * qt[j]
        centres.append(i)
        j += 1
    w = solve_triangular(r_mat[:j, :j], np.asarray(proj[:j]))
    return RbfNetwork(centres=u[centres], weights=w[1:], bias=float(w[0]), b=b, mean=mean,
                      std=std, mse=float(np.mean(resid ** 2)))


# --------------------------------------------------------------------------- entry


def interpolate(method: str, xy: np.ndarray, z: np.ndarray, query_xy: np.ndarray, *,
                kriging_cfg: KrigingConfig = KrigingConfig(), rbf_cfg: RbfConfig = RbfConfig(),
                rbfnn_cfg: RbfnnConfig = RbfnnConfig(), idw_neighbours: int = 8,
                idw_power: float = 2.0, intensity: np.ndarray | None = None,
                query_intensity: np.ndarray | None = None,
                rng: np.random.Generator | int | None = SAMPLING_SEED,
                variogram: Variogram | None = None) -> np.ndarray:
    """Interpolate samples (xy (N, 2) metres, z (N,) metres) at query_xy (M, 2) metres.

    method: one of METHODS. Returns (M,) float64, NaN where the method is undefined
    (outside the hull for ``tin``, no samples at all). ``rbfnn`` takes intensity (N,),
    when given, as a third input, as the paper did; the queries' own intensity (M,) is
    then needed too (missing: the nearest sample's). A DEM's empty cells have no
    intensity, so only check points can be interpolated this way. ``rbfnn`` trains on at
    most ``rbfnn_cfg.max_train`` random samples (drawn with ``rng``) and answers within
    their range of heights. Raises
    CloudFormatError for bad shapes or an unknown method. ``variogram``: for ``kriging``,
    use this one instead of fitting one to the samples (see :func:`kriging_variogram`).
    """
    if method not in METHODS:
        raise CloudFormatError(f"interpolate: unknown method {method!r}; expected one of "
                               f"{', '.join(METHODS)}")
    xy, z, q = _check(xy, z, query_xy)
    use_int = method == "rbfnn" and intensity is not None
    if use_int:
        xy, z, inten = merge_coincident(xy, z, extra=np.asarray(intensity, dtype=np.float64))
    else:
        xy, z = merge_coincident(xy, z)
    if len(xy) == 0 or len(q) == 0:
        return np.full(len(q), np.nan)
    if method == "tin":
        return tin(xy, z, q)
    if method == "idw" or len(xy) == 1:
        return idw(xy, z, q, neighbours=idw_neighbours, power=idw_power)
    if method == "kriging":
        return kriging(xy, z, q, cfg=kriging_cfg, rng=rng, variogram=variogram)
    if method == "rbf":
        return rbf(xy, z, q, cfg=rbf_cfg)
    inputs, query_inputs = xy, q
    if use_int:
        if query_intensity is None:
            _, near = tree_query(cKDTree(xy), q, k=1, workers=-1)
            query_intensity = inten[near]
        inputs = np.column_stack([xy, inten])
        query_inputs = np.column_stack([q, np.asarray(query_intensity, dtype=np.float64)])
    if len(z) > rbfnn_cfg.max_train:
        pick = np.random.default_rng(rng).choice(len(z), rbfnn_cfg.max_train, replace=False)
        inputs, z = inputs[pick], z[pick]
    net = train_rbfnn(inputs, z, goal=rbfnn_cfg.goal, spread=rbfnn_cfg.spread,
                      max_neurons=rbfnn_cfg.max_neurons)
    # A bias plus Gaussian bumps has no trend to carry beyond the samples: outside their
    # range it only overshoots (ISPRS samp11: 13 m below the lowest sample).
    return np.clip(net.predict(query_inputs), z.min(), z.max())
