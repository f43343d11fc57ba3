"""numpy without its slow paths: column-wise reductions, a closed-form 3 x 3 PCA,
single-threaded BLAS (its thread pools found once), and freed memory handed back.

numpy 2.4 reduces an (N, 3) array along axis 0 row by row: ``xyz.min(axis=0)`` on 50 000
points takes ~1.8 ms, one column at a time ~0.08 ms (23 x). A cloud passes through dozens
of such reductions per message, so the hot paths use these instead.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import signal
import threading
from typing import TYPE_CHECKING, Any, Iterator, Literal

import numpy as np
from numpy.typing import ArrayLike

from lidar_obstacles.errors import CloudFormatError

if TYPE_CHECKING:
    from scipy.spatial import cKDTree
    from threadpoolctl import ThreadpoolController


# What `points_xyz` does with a row holding a NaN or an infinity (see there).
NonFinite = Literal["refuse", "drop", "keep"]


def points_xyz(xyz: ArrayLike, what: str, *, columns: int | None = 3, min_points: int = 0,
               nonfinite: NonFinite = "refuse") -> np.ndarray:
    """``xyz`` as an (N, columns) float64 array (no copy when it is one already): the
    package's one check of the point arrays handed to it.

    xyz: (N, 3) points in metres by default; (N, 2) xy in metres with ``columns=2``;
    (N, D) of any D >= 1 with ``columns=None`` (features, in their own units).
    what: the argument as the error names it ("simplify: xyz").
    min_points: the fewest rows accepted (1 where nothing can be made of none: a k-means,
    a picture).
    nonfinite: what becomes of a row with a NaN or an infinity:

    - "refuse": CloudFormatError, saying how many (a NaN must not reach a plane fit: an
      SVD that does not converge says nothing of the cloud);
    - "drop": the row is left out (a copy only then: the DEM takes what ground it gets);
    - "keep": passed on as it is (a pure evaluation: NaN in gives NaN out).

    CloudFormatError, naming ``what`` and the shape or dtype received, for another shape
    (an (N, 6) array must not pass as 2N points, nor an (N,) one as N / 3), too few rows,
    or values other than integers and floats (a bool mask, strings, objects)."""
    try:
        arr = np.asarray(xyz)
    except ValueError as exc:  # (ragged nested lists)
        raise CloudFormatError(f"{what}: not an array of numbers ({exc})") from None
    width_ok = arr.ndim == 2 and (arr.shape[1] >= 1 if columns is None
                                  else arr.shape[1] == columns)
    if not width_ok or arr.shape[0] < min_points:
        want = "(N, D)" if columns is None else f"(N, {columns})"
        at_least = f" with N >= {min_points}" if min_points > 0 else ""
        raise CloudFormatError(f"{what}: expected points of shape {want}{at_least}, "
                               f"got {arr.shape}")
    if arr.dtype.kind not in "iuf":
        raise CloudFormatError(f"{what}: expected numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if nonfinite == "keep" or np.isfinite(arr).all():
        return arr
    finite = all_columns(np.isfinite(arr))  # (one column at a time: see the module's doc)
    if nonfinite == "drop":
        return arr[finite]
    bad = len(arr) - int(np.count_nonzero(finite))
    raise CloudFormatError(f"{what}: {bad} of {len(arr)} points have a NaN or infinite "
                           "coordinate (drop them first)")


def column_min(a: np.ndarray) -> np.ndarray:
    """(K,) minimum of each column of (N, K) a (N >= 1)."""
    return np.array([a[:, j].min() for j in range(a.shape[1])])


def column_max(a: np.ndarray) -> np.ndarray:
    """(K,) maximum of each column of (N, K) a (N >= 1)."""
    return np.array([a[:, j].max() for j in range(a.shape[1])])


def column_mean(a: np.ndarray) -> np.ndarray:
    """(K,) float64 mean of each column of (N, K) a (N >= 1)."""
    return np.array([a[:, j].mean(dtype=np.float64) for j in range(a.shape[1])])


def all_columns(mask: np.ndarray) -> np.ndarray:
    """(N,) bool: every column of (N, K) bool mask true."""
    out = mask[:, 0].copy()
    for j in range(1, mask.shape[1]):
        out &= mask[:, j]
    return out


def row_norm(a: np.ndarray) -> np.ndarray:
    """(N,) Euclidean norm of each row of (N, K) float a."""
    total = a[:, 0] * a[:, 0]
    for j in range(1, a.shape[1]):
        total += a[:, j] * a[:, j]
    return np.sqrt(total)


# How far below a cell's edge (in cells) a coordinate still counts as on it: cell_index.
CELL_SLACK = 1e-6


def cell_index(offset: np.ndarray, edge: float) -> np.ndarray:
    """int64 cell indices of offsets (any shape, metres from the grid's corner) in cells of
    `edge` m: floor(offset / edge), an offset within CELL_SLACK cells below an edge counted
    on it.

    Why: survey coordinates lie on a lattice (LAS: 1 cm or 1 mm steps), so many points
    lie exactly on the edges of cells counted from a lattice point (the cloud's lowest
    point, a whole metre): heights in cm on 0.25 m voxels, one in 25. Which side of the
    edge such a point fell on was decided by the binary rounding of its coordinates,
    ~1e-13 to 1e-9 m, and that rounding changes when the cloud is moved (AHN4 moved
    2 000 m up: 28 of its obstacle points changed voxel, and 603 their class). The slack,
    0.25 um on 0.25 m voxels, is far above that rounding and far below any scan's
    resolution."""
    return np.floor(offset / edge + CELL_SLACK).astype(np.int64)


def lowest_per_cell(xyz: np.ndarray, origin: np.ndarray, cell: float) -> np.ndarray:
    """(C,) int64 indices of the lowest of (P, 3) points xyz (m) in each occupied XY cell
    of `cell` m counted from `origin` (2,) m (`cell_index`: a point on a cell's edge falls
    in the same cell wherever the cloud lies), in the cells' order (x, then y)."""
    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    ij = cell_index(xyz[:, :2] - origin, cell)
    ij -= column_min(ij)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((xyz[:, 2], key))
    return order[np.r_[True, key[order][1:] != key[order][:-1]]]


def snap_micrometres(a: np.ndarray) -> np.ndarray:
    """a (any shape, metres) rounded to the micrometre, in place; returns a."""
    a *= 1e6
    np.round(a, out=a)
    a /= 1e6
    return a


# A grid over a cloud holds at most this many cells per point (and SPARSE_MIN_CELLS
# whatever the points): a cloud far sparser than its grid is gridded on coarser cells
# (`sparse_grid_cell`). A driver's millimetres taken for metres makes such clouds. Real
# scans lie far below it: ISPRS's sparsest sample, samp53, has ~6 cells of 1 m per point.
SPARSE_CELLS_PER_POINT = 64
SPARSE_MIN_CELLS = 250_000


def sparse_grid_cell(cell: float, lo: np.ndarray, hi: np.ndarray, n: int) -> float:
    """The cell (m) for a grid over the box lo..hi ((2,) m) of n points: `cell`, or its
    smallest whole multiple that keeps the grid within max(SPARSE_MIN_CELLS,
    SPARSE_CELLS_PER_POINT n) cells when `cell` would make more."""
    cells = float(np.prod(np.floor((np.asarray(hi) - np.asarray(lo)) / cell) + 1))
    limit = max(SPARSE_MIN_CELLS, SPARSE_CELLS_PER_POINT * n)
    return cell if cells <= limit else cell * float(np.ceil(np.sqrt(cells / limit)))


def distinct_points(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The distinct points of xyz (N, 3) float64: (first (U,) the index of each one's first
    occurrence, ascending, and inverse (N,) which of them each point is), or None when no
    two points are equal (the usual case).

    By a hash of the coordinates' bits, not a lexicographic sort of all points (np.lexsort
    of three columns: ~11 ms for 50 000 points): only the points whose hash shares a bucket
    of a table of >= 4 N with another's are sorted, by the whole hash (~0.7 ms in all).
    Equal hashes of unequal points (a collision, ~N^2 / 2^64) are sorted by their
    coordinates instead."""
    n = len(xyz)
    if n < 2:
        return None
    bits = np.ascontiguousarray(xyz + 0.0).view(np.uint64)  # (+ 0.0: -0.0 is 0.0)
    key = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    key ^= bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
    key ^= bits[:, 2] * np.uint64(0x165667B19E3779F9)
    width = int(n).bit_length() + 2  # a table of 2^width >= 4 N buckets: ~1 / 6 of the
    # points of an ordinary cloud share one with another
    bucket = (key >> np.uint64(64 - width)).astype(np.intp)
    cand = np.flatnonzero(np.bincount(bucket, minlength=1 << width)[bucket] > 1)
    if len(cand) == 0:
        return None
    ckey = key[cand]
    order = np.argsort(ckey, kind="stable")  # (stable: the first occurrence leads)
    same = ckey[order[1:]] == ckey[order[:-1]]
    if not same.any():
        return None
    pts = xyz[cand[order]]
    equal = all_columns(pts[1:] == pts[:-1])
    if (same & ~equal).any():  # a collision: sort by the coordinates themselves
        c = xyz[cand]
        order = np.lexsort((c[:, 2], c[:, 1], c[:, 0]))  # (stable too)
        pts = c[order]
        equal = all_columns(pts[1:] == pts[:-1])
    else:
        equal &= same
    if not equal.any():
        return None
    sorted_idx = cand[order]
    lead = np.concatenate([[0], np.flatnonzero(~equal) + 1])  # each group's first position
    group = np.cumsum(np.concatenate([[False], ~equal]))  # (C,) group of each sorted point
    rep = np.arange(n)
    rep[sorted_idx] = sorted_idx[lead][group]
    first = np.flatnonzero(rep == np.arange(n))
    position = np.empty(n, np.int64)
    position[first] = np.arange(len(first))
    return first, position[rep]


TABLE_MAX = 1 << 22  # cells of unique_ints' counting table (64 MB)


def unique_ints(keys: np.ndarray, table_ratio: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(keys, return_inverse=True) of (N,) non-negative integer keys: (U,) the
    sorted distinct keys and (N,) the index of each key among them.

    Keys of a small grid (at most table_ratio x N cells, such as a message's 2 m cells) are
    counted in a table, not sorted: 8 x faster for 30 000 points in 5 000 cells. A fresh
    table much larger than N costs more in page faults and cache misses than the sort
    saves; keys of nearby points (voxels of a scan in its order) stay cheaper up to ~8 x N
    (a forest strip's 51 000 points in 0.75 m voxels, a box of 268 000: 0.8 ms, sorted
    2.7 ms; in 0.25 m voxels, a box of 7 100 000: 41 ms, sorted 2.7 ms). Never a table of
    more than TABLE_MAX cells (16 bytes each, while it lives): a survey tile's millions
    of points are sorted."""
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    size = int(keys.max()) + 1
    if size > min(table_ratio * len(keys), TABLE_MAX):
        distinct, inverse = np.unique(keys, return_inverse=True)
        return distinct, inverse.ravel()
    present = np.flatnonzero(np.bincount(keys, minlength=size))
    rank = np.zeros(size, np.int64)
    rank[present] = np.arange(len(present))
    return present, rank[keys]


@functools.cache
def thread_pools(*native: str) -> ThreadpoolController:
    """The BLAS and OpenMP thread pools of this process, found once, after importing the
    modules `native` (e.g. "sklearn.cluster", whose OpenMP runtime is to be among them).
    Finding them scans every loaded library, ~2.4 ms, which ``threadpool_limits`` pays on
    each call; limiting them through the controller returned costs ~0.02 ms."""
    import importlib

    from threadpoolctl import ThreadpoolController

    for module in native:
        importlib.import_module(module)
    return ThreadpoolController()


def single_threaded_blas() -> None:
    """Run BLAS on one thread in this process (the nodes and the CLI call it at start).

    The core's matrix products are small (RANSAC's points x candidate planes, 3 x 3
    covariances); OpenBLAS's worker threads spin on the 2 cores the nodes share with the
    flight stack and with each other: a (3000, 3) @ (3, 100) product took 8 ms with 2
    threads on a busy machine and 0.15 ms with one, and the detector's CPU time per
    50 000-point message fell from 54 to 33 ms.

    Only the libraries not on one thread already are set: setting OpenBLAS's thread
    count, even to the 1 it has, in a forked child starts its worker threads again, and
    they spin ~0.1 s each before they sleep (0.2 s of CPU per `replay` worker, whose
    parent had set it before the fork)."""
    from threadpoolctl import threadpool_info, threadpool_limits

    busy = {lib["prefix"]: 1 for lib in threadpool_info()
            if lib["user_api"] == "blas" and lib["num_threads"] > 1}
    if busy:
        threadpool_limits(busy)


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None where the C library has none (musl, macOS)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3


def reuse_freed_memory() -> bool:
    """Let this process reuse the memory of freed arrays rather than hand it back at once
    (the nodes and the CLI call it at start; forked workers inherit it). True when set.

    glibc maps big blocks (a cloud's arrays, 0.4-20 MB) fresh and unmaps them when freed,
    and trims the heap's top eagerly, so every message faults its pages in again (~1 us
    per 4 KB page, more with two processes faulting at once in a VM). With blocks up to
    32 MB kept on the heap, a 256 MB trim threshold and a 64 MB top pad they are reused:
    `replay` of the simulated 10 Hz flight went from 1.75-2.14 to 2.17-2.55 x real time
    (2.9-3.3 to 3.6-4.0 x without the DEM). Memory stays flat: `release_free_memory`
    still hands the free pages back every 10 s."""
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False  # not glibc (musl, macOS): its own policy stands
    return all(mallopt(option, value) == 1 for option, value in (
        (_M_MMAP_THRESHOLD, 32 << 20), (_M_TRIM_THRESHOLD, 256 << 20), (_M_TOP_PAD, 64 << 20)))


def release_free_memory() -> None:
    """Give the heap's free pages back to the system (the nodes call it every 10 s).

    Each cloud allocates and frees tens of MB of arrays of varying sizes; glibc keeps the
    freed pages, fragmented, and the resident size crept up over a long flight (8 % in
    4 simulated minutes, 137 -> 163 MB); trimmed, it stayed at 108 -> 116 MB. Not more
    often: the next cloud faults its pages back in (~10 ms more on a 30 ms message)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


# The signals that stop the programs: held while SciPy's threads work on our arrays.
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM noted, not acted on, while the block runs; delivered after it,
    to the handlers there were before. A no-op off the main thread (only the main thread
    runs Python's signal handlers, and only it may set them)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    before = {s: signal.signal(s, lambda signum, frame: received.append(signum))
              for s in _STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
        for signum in dict.fromkeys(received):  # each once, in the order they came
            signal.raise_signal(signum)


def tree_query(tree: cKDTree, x: np.ndarray, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
    """`tree.query(x, **kwargs)` (distances, indices) for (Q, D) query points `x` in the
    tree's units; a query on several threads
    (`workers` other than 1) runs with the stop signals held (`stop_signals_held`).

    Why: SciPy runs a parallel query in Python threads and joins them. A Ctrl-C raised in
    the join unwound the caller, whose arrays were freed under the threads still writing
    them: a segfault after "interrupted" (status 139 for 130) in 2 of ~40 runs of
    `evaluate --report` stopped mid-way. A query takes milliseconds; the stop waits that
    long."""
    if kwargs.get("workers", 1) == 1:
        return tree.query(x, **kwargs)
    with stop_signals_held():
        return tree.query(x, **kwargs)


def symmetric_eig3(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (M, 3) descending and the unit eigenvectors (M, 3) of the largest and the
    smallest, of (M, 3, 3) symmetric matrices (covariances: m^2), in closed form (Smith
    1961). The batched PCA of the package: the obstacles' shapes, the simplifier's normals
    and the feature points' reference planes.

    ~3 x faster than batched ``np.linalg.eigh``, whose per-matrix LAPACK call was the
    largest cost of the wire search."""
    values = symmetric_eigenvalues3(cov)
    return values, eigenvector3(cov, values[:, 0]), eigenvector3(cov, values[:, 2])


def symmetric_eigenvalues3(cov: np.ndarray) -> np.ndarray:
    """Eigenvalues (M, 3), descending, of (M, 3, 3) symmetric matrices (Smith 1961)."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 ** 2 + a02 ** 2 + a12 ** 2
    p = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b00, b11, b22 = (a00 - q) / safe, (a11 - q) / safe, (a22 - q) / safe
    b01, b02, b12 = a01 / safe, a02 / safe, a12 / safe
    det_b = (b00 * (b11 * b22 - b12 ** 2) - b01 * (b01 * b22 - b12 * b02)
             + b02 * (b01 * b12 - b11 * b02))
    phi = np.arccos(np.clip(det_b / 2.0, -1.0, 1.0)) / 3.0
    l1 = q + 2.0 * p * np.cos(phi)
    l3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.column_stack([l1, 3.0 * q - l1 - l3, l3])


def eigenvector3(cov: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (M, 3) of (M, 3, 3) symmetric matrices for their eigenvalues lam
    (M,); vertical where any direction is one (isotropic)."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    # The eigenvector is orthogonal to the rows of A - lam I: the longest cross product of
    # two rows is the best conditioned choice.
    r0 = np.column_stack([a00 - lam, a01, a02])
    r1 = np.column_stack([a01, a11 - lam, a12])
    r2 = np.column_stack([a02, a12, a22 - lam])
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)])
    norms = np.linalg.norm(cands, axis=2)
    best = norms.argmax(axis=0)
    idx = np.arange(len(lam))
    v, nv = cands[best, idx], norms[best, idx]
    out = np.zeros_like(v)
    ok = nv > 0
    out[ok] = v[ok] / nv[ok, None]
    out[~ok] = (0.0, 0.0, 1.0)
    return out
