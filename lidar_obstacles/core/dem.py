"""The DEM: ground points -> a float32 elevation grid, offline or rolling with the vehicle.

Grid conventions (grid_map's ideas): cell (row, col) covers
x in [origin_x + col*res, origin_x + (col+1)*res), y in [origin_y + row*res, ...), so
row index = y and row 0 is the SOUTH edge; the origin is a multiple of the resolution so
grids of different messages and surveys line up. Layers: ``elevation`` float32 (NaN =
unknown), ``interpolated`` uint8 (1 = filled by the interpolator, 0 = measured or
unknown), ``count`` uint32 (ground points in the cell).

A measured cell is the mean ground z of its points. Empty cells within
``dem.fill_distance`` of a measured cell are interpolated from the measured cells (each
at the mean x, y, z of its points, so sloping cells are not biased towards the centre).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from lidar_obstacles.config import DemBuilderConfig, KrigingConfig, ThinningConfig
from lidar_obstacles.core.arrays import (column_max, column_min, points_xyz, tree_query,
                                         unique_ints)
from lidar_obstacles.core.interpolate import (Variogram, degeneracy, interpolate,
                                              kriging_variogram, merge_coincident,
                                              neighbour_residual)
from lidar_obstacles.errors import ConfigError


@dataclass(frozen=True)
class DemGrid:
    """A frozen DEM.

    elevation: (rows, cols) float32 metres, NaN where unknown. interpolated: (rows, cols)
    uint8, 1 where filled by interpolation. count: (rows, cols) uint32 ground points per
    cell. origin: (2,) float64 x, y of the lower-left corner of cell (0, 0), metres.
    resolution: cell edge, metres. reason: why the DEM is empty or flat ("" otherwise).
    """

    elevation: np.ndarray
    interpolated: np.ndarray
    count: np.ndarray
    origin: np.ndarray
    resolution: float
    reason: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the grid."""
        return self.elevation.shape  # type: ignore[return-value]

    def cell_centres(self) -> np.ndarray:
        """(rows, cols, 2) float64 x, y of every cell centre, metres."""
        rows, cols = self.shape
        xs = self.origin[0] + (np.arange(cols) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(rows) + 0.5) * self.resolution
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx, gy], axis=-1)

    def sample(self, xy: np.ndarray) -> np.ndarray:
        """(M,) float64 bilinear elevation at xy (M, 2) metres between cell centres; NaN
        outside the cell centres' hull or next to an unknown cell (`grid_values_at`)."""
        from lidar_obstacles.core.metrics import grid_values_at

        return grid_values_at(self.elevation, np.asarray(xy, np.float64).reshape(-1, 2),
                              resolution=self.resolution, origin=tuple(self.origin))


def empty_grid(resolution: float, reason: str) -> DemGrid:
    """A 0 x 0 DEM carrying the reason it is empty."""
    return DemGrid(np.zeros((0, 0), np.float32), np.zeros((0, 0), np.uint8),
                   np.zeros((0, 0), np.uint32), np.zeros(2), float(resolution), reason)


def accuracy(predicted: np.ndarray, truth: np.ndarray) -> tuple[float, float, int]:
    """(RMSE metres, R^2, n used) over the finite pairs of predicted and true elevations,
    two arrays of the same shape (any), metres (NaN when none, R^2 too when the truth is
    constant): `grid_errors`' figures."""
    from lidar_obstacles.core.metrics import grid_errors

    e = grid_errors(np.asarray(truth, np.float64), np.asarray(predicted, np.float64))
    nan = float("nan")
    return (nan if e["rmse_m"] is None else e["rmse_m"],
            nan if e["r2"] is None else e["r2"], e["n"])


# --------------------------------------------------------------------------- thinning


@dataclass(frozen=True)
class Thinning:
    """Indices into the ground points: keep (K,) int64 kept for interpolation, check (C,)
    int64 held out to measure the DEM (never in keep)."""

    keep: np.ndarray
    check: np.ndarray


def tin_curvature(xyz: np.ndarray) -> np.ndarray:
    """(N,) float64 |z - the plane of the Delaunay neighbours at the point| (m,
    :func:`neighbour_residual`): large where the terrain bends, 0 on any plane. Zeros
    when the points cannot be triangulated."""
    n = len(xyz)
    if degeneracy(xyz[:, :2]):
        return np.zeros(n)
    try:
        tri = Delaunay(xyz[:, :2] - xyz[:, :2].mean(axis=0))  # centred: conditioning
    except QhullError:
        return np.zeros(n)
    return neighbour_residual(xyz, *tri.vertex_neighbor_vertices)


def thin(xyz: np.ndarray, *, cfg: ThinningConfig,
         rng: np.random.Generator | int | None = None) -> Thinning:
    """Hold out ``cfg.check_points`` random points, then keep ``cfg.keep`` of the rest.

    ``random`` keeps a uniform random share; ``curvature`` draws without replacement with
    weight 0.25 + curvature / mean curvature (see :func:`tin_curvature`), so bends, ditches
    and breaklines keep more points while flat ground still keeps some (weighted sampling
    by the Efraimidis-Spirakis keys log(u) / w, one vectorised pass).

    xyz: (N, 3) float64 ground points, metres. Returns sorted indices into them.
    """
    gen = np.random.default_rng(cfg.seed if rng is None else rng)
    n = len(xyz)
    n_check = min(cfg.check_points, max(n - 3, 0))
    if cfg.keep >= 1.0:  # (the node's default) only the check points to draw: no shuffle
        check = np.sort(gen.choice(n, n_check, replace=False))
        keep = np.ones(n, bool)
        keep[check] = False
        return Thinning(keep=np.flatnonzero(keep), check=check)
    order = gen.permutation(n)
    check, rest = order[:n_check], order[n_check:]
    n_keep = int(round(cfg.keep * len(rest)))
    if cfg.method == "random" or n_keep >= len(rest):
        keep = rest[:n_keep]
    else:
        curv = tin_curvature(xyz[rest])
        mean = curv.mean()
        weight = 0.25 + (curv / mean if mean > 0 else 0.0)
        keys = np.log(gen.random(len(rest))) / weight
        keep = rest[np.argpartition(-keys, n_keep - 1)[:n_keep]] if n_keep > 0 else rest[:0]
    return Thinning(keep=np.sort(keep), check=np.sort(check))


class CheckPoints:
    """Ground points held out of a rolling DEM to measure it (the paper's check points),
    the newest ``capacity`` of them: (C, 3) float64 metres."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self.xyz = np.zeros((0, 3))

    def add(self, xyz: np.ndarray) -> None:
        """Hold out xyz (K, 3) m too; the oldest go beyond ``capacity``."""
        if self.capacity > 0:
            self.xyz = np.concatenate([self.xyz, xyz])[-self.capacity:]

    def accuracy(self, grid: DemGrid) -> dict[str, float | int | None]:
        """RMSE (m) and R^2 of the grid's elevation (nearest cell) at the check points
        inside it with a known elevation, and how many that is (check_n). The cell's
        value, as a consumer of the published grid reads it at a position (grid_map's
        default too), and every known cell counts, edges included; `evaluate` reads its
        DEMs bilinearly (`DemGrid.sample`), which leaves the half cell at an edge out."""
        if len(self.xyz) == 0 or grid.elevation.size == 0:
            return {"check_rmse_m": None, "check_r2": None, "check_n": 0}
        rows, cols = grid.elevation.shape
        c = np.floor((self.xyz[:, 0] - grid.origin[0]) / grid.resolution).astype(np.int64)
        r = np.floor((self.xyz[:, 1] - grid.origin[1]) / grid.resolution).astype(np.int64)
        inside = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
        est = np.full(len(self.xyz), np.nan)
        est[inside] = grid.elevation[r[inside], c[inside]]
        rmse, r2, n = accuracy(est, self.xyz[:, 2])
        return {"check_rmse_m": None if n == 0 else rmse,
                "check_r2": None if n == 0 or not np.isfinite(r2) else r2, "check_n": n}


# --------------------------------------------------------------------------- ground blunders


# Two neighbouring patch cells belong to one surface when their lowest points differ by
# at most _PATCH_STEP + _PATCH_SLOPE * their distance (45 degrees: steep natural ground
# still joins, a 3 m wall between 2 m cells does not).
_PATCH_STEP = 0.5  # m
_PATCH_SLOPE = 1.0  # rise over run
# Patch cells are this many point spacings wide (and at least _PATCH_MIN_CELL): 1 m cells
# split the sparse ISPRS ground (1-3.5 m spacing) into fragments and the test then
# dropped real ground (samp12 end-to-end RMSE 0.79 -> 2.45 m, samp61 0.74 -> 2.32 m).
_PATCH_SPACINGS = 2.0
_PATCH_MIN_CELL = 2.0  # m
# A patch is judged against the highest (lowest) of the this many main-surface cells
# nearest to each of its cells, not the nearest one alone: real ground cut off on a
# slope stands above the ground downhill but not above the ground uphill (ISPRS samp53
# terraces: RMSE 2.474 m judged by the nearest cell, 2.429 m by 16, as with no test;
# samp23 0.882 -> 0.867 m). Roofs and crowns stand above all the ground around them.
_PATCH_NEIGHBOURS = 16


def _point_spacing(x: np.ndarray, y: np.ndarray) -> float:
    """Mean point spacing (m) of points x, y (N,) metres from their lower corner: sqrt(area
    of the occupied 4 m cells / N)."""
    # (np.floor(x / c) rather than x // c: numpy's float floor_divide is 2.5 x slower)
    ix, iy = np.floor(x / 4.0).astype(np.int64), np.floor(y / 4.0).astype(np.int64)
    occupied = np.count_nonzero(np.bincount(iy * (int(ix.max()) + 1) + ix))
    return float(np.sqrt(occupied * 16.0 / len(x)))


def band_allowance(xyz: np.ndarray, height_above_ground: np.ndarray) -> np.ndarray:
    """(N,) m: how far the detector's ground surface may lie from the ground points xyz
    (N, 3) float64 metres that it was measured at: point spacing x the surface's slope.

    The surface is sampled at the points (z - height_above_ground (N,) m, NaN skipped) and
    averaged over cells of 2 point spacings (at least 2 m); a point's slope is the median
    rise from its cell to the 4 neighbouring cells, per metre: on a plane of slope s that
    is s/2 to s/sqrt(2), while a jump on one side (a roof the filter took for ground) does
    not count. Between points 2-3 m apart on
    steep ground (the ISPRS rural samples) the filter's surface is in-painted and true
    ground stands metres off it, while on dense scans (AHN, 0.2-0.3 m) the allowance is a
    few centimetres.
    """
    surface = xyz[:, 2] - np.asarray(height_above_ground, np.float64)
    ok = np.flatnonzero(np.isfinite(surface))  # a NaN height counts as on the surface
    out = np.zeros(len(xyz))
    if len(ok) < 2:
        return out
    lo = column_min(xyz[ok, :2])
    x, y = xyz[ok, 0] - lo[0], xyz[ok, 1] - lo[1]
    spacing = _point_spacing(x, y)
    cell = max(_PATCH_MIN_CELL, _PATCH_SPACINGS * spacing)
    # a spare row and column on each side: the shifted views below never wrap
    ix, iy = np.floor(x / cell).astype(np.int64) + 1, np.floor(y / cell).astype(np.int64) + 1
    shape = (int(iy.max()) + 2, int(ix.max()) + 2)
    flat = iy * shape[1] + ix
    total = np.bincount(flat, weights=surface[ok], minlength=shape[0] * shape[1])
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore"):
        mean = (total / count).reshape(shape)  # NaN in empty cells
    centre = mean[1:-1, 1:-1]
    rises = np.sort([np.abs(other - centre) for other in
                     (mean[2:, 1:-1], mean[:-2, 1:-1], mean[1:-1, 2:], mean[1:-1, :-2])], axis=0)
    # median of the known rises (NaN sorts last; np.nanmedian is 5 x slower here): of n
    # known ones, the mean of those at (n - 1) // 2 and n // 2; none known (an isolated
    # cell) gives 0
    known = np.count_nonzero(np.isfinite(rises), axis=0)
    low = np.take_along_axis(rises, np.maximum(known - 1, 0)[None] // 2, axis=0)[0]
    high = np.take_along_axis(rises, (known // 2)[None], axis=0)[0]
    typical = np.where(known > 0, 0.5 * (low + high), 0.0)
    out[ok] = spacing * typical[iy - 1, ix - 1] / cell
    return out


def ground_blunders(xyz: np.ndarray, *, max_area: float, rise: float,
                    sink: float) -> np.ndarray:
    """(N,) bool: ground points (N, 3) float64 metres in small patches that stand apart
    from the main ground surface: structure tops, tree crowns or bridge decks taken for
    ground (raised), and clusters of low blunders (sunk).

    The points are binned into cells of 2 point spacings (at least 2 m), each cell at its
    lowest point; neighbouring cells (8-connected) whose lowest points differ by at most
    0.5 m + 1.0 x their distance are one surface. Every surface but the largest is a
    candidate patch: it is dropped when its area is at most ``max_area`` m^2 and more than
    half its cells lie more than ``rise`` m above the highest (all its points go), or more
    than ``sink`` m below the lowest (its points that far down go), of the 16 cells of the
    largest surface nearest to them. So a patch needs a step all around it (a smooth ramp
    joins it to the ground) and must stand above (below) all the ground around it,
    however wide the gap between them (kriging would otherwise spread it over that gap).
    ``max_area`` 0 drops nothing.
    """
    if len(xyz) < 2 or max_area <= 0:
        return np.zeros(len(xyz), bool)
    # one column at a time: numpy reduces an (N, 2) array row by row (core.arrays)
    lo = column_min(xyz[:, :2])
    x, y = xyz[:, 0] - lo[0], xyz[:, 1] - lo[1]
    cell = max(_PATCH_MIN_CELL, _PATCH_SPACINGS * _point_spacing(x, y))
    ix, iy = np.floor(x / cell).astype(np.int64), np.floor(y / cell).astype(np.int64)
    cols = int(ix.max()) + 3  # a spare column on each side: offsets never wrap
    cells, inverse = unique_ints((iy + 1) * cols + ix + 1)
    zmin = np.full(len(cells), np.inf)
    np.minimum.at(zmin, inverse, xyz[:, 2])
    u = len(cells)
    src, dst = [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        pos = np.searchsorted(cells, cells + dr * cols + dc)
        pos = np.minimum(pos, u - 1)
        hit = cells[pos] == cells + dr * cols + dc
        a, b = np.flatnonzero(hit), pos[hit]
        step = _PATCH_STEP + _PATCH_SLOPE * cell * float(np.hypot(dr, dc))
        near = np.abs(zmin[a] - zmin[b]) <= step
        src.append(a[near])
        dst.append(b[near])
    s, d = np.concatenate(src), np.concatenate(dst)
    graph = coo_matrix((np.ones(len(s)), (s, d)), shape=(u, u))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    main = label == int(np.argmax(size))
    if main.all():
        return np.zeros(len(xyz), bool)
    centre = np.column_stack([cells % cols, cells // cols]).astype(np.float64)
    k = min(_PATCH_NEIGHBOURS, int(main.sum()))
    _, nearest = tree_query(cKDTree(centre[main]), centre[~main], k=k, workers=-1)
    around = zmin[main][nearest.reshape(-1, k)]
    top, bottom = zmin.copy(), zmin.copy()  # per cell: the main surface around it
    top[~main], bottom[~main] = around.max(axis=1), around.min(axis=1)
    high = np.bincount(label, weights=zmin - top > rise, minlength=len(size))
    low = np.bincount(label, weights=zmin - bottom < -sink, minlength=len(size))
    small = size * cell * cell <= max_area
    raised, sunk = small & (high > 0.5 * size), small & (low > 0.5 * size)
    # A raised patch goes whole (a crown's points spread over metres); of a sunk one only
    # the points that far down: a cell of low blunders also holds the ground above them.
    return raised[label][inverse] | (sunk[label][inverse]
                                     & (xyz[:, 2] - bottom[inverse] < -sink))


# --------------------------------------------------------------------------- grids


# The variogram describes the terrain's roughness and the survey's noise, which change
# over hundreds of metres, not from one message to the next; fitting it (binned fit plus
# the nugget's cross-validation) cost as much as the kriging itself (~90 of ~170 ms per
# 50 000-point message on the AHN corridor), so a rolling DEM refits it every 10 updates.
_REFIT_EVERY = 10

# The seed of the interpolation's random draws (the kriging variogram's sample pairs and
# held-out samples, the RBF network's training points): fixed, so the same ground gives
# the same DEM in every run. Passed as an int, not a generator: each fit draws afresh, so
# a rolling DEM's fill does not depend on how many fits came before it.
INTERPOLATION_SEED = 0


class _VariogramCache:
    """The kriging variogram of a rolling DEM, refitted every ``_REFIT_EVERY`` uses or
    when the kriging parameters change."""

    def __init__(self) -> None:
        self._vg: Variogram | None = None
        self._cfg: KrigingConfig | None = None
        self._uses = 0

    def get(self, xy: np.ndarray, z: np.ndarray, cfg: KrigingConfig) -> Variogram:
        """The cached variogram, or one fitted to samples xy (N, 2) m, z (N,) m."""
        if self._vg is None or self._uses >= _REFIT_EVERY or cfg != self._cfg:
            self._vg = kriging_variogram(xy, z, cfg=cfg, rng=INTERPOLATION_SEED)
            self._cfg, self._uses = cfg, 0
        self._uses += 1
        return self._vg


_CELL_BYTES = 32  # a _Cells cell: count 4, sums 3 x 8, interpolated layer 4


class DemTooLarge(ConfigError):
    """The DEM of the whole survey (`RollingDem`'s `whole`) would pass `dem.max_cells`
    (`too_large_message` says by how much, once the survey's span is known)."""


def too_large_message(lo: np.ndarray, hi: np.ndarray, cfg: DemBuilderConfig) -> str:
    """What to change for a survey whose points span lo..hi ((2,) x, y m) to fit in one
    DEM: the cells that cover it at `dem.resolution`, against `dem.max_cells`, and the
    resolution at which it would fit."""
    res, limit = cfg.dem.resolution, cfg.dem.max_cells
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    span = hi - lo

    def cells_at(r: float) -> int:  # (as RollingDem frames the survey)
        return int(np.prod(np.floor(hi / r) - np.floor(lo / r) + 1))

    cells = cells_at(res)
    # from the area's estimate (the edge cells aside), up in steps of two significant
    # figures until the grid fits, edge cells and all
    fits = max(float(np.sqrt(span[0] * span[1] / limit)), float(span.max()) / limit, res)
    step = 10.0 ** (int(np.floor(np.log10(fits))) - 1)
    fits = float(np.ceil(fits / step) * step)
    while cells_at(fits) > limit:
        fits = float(np.round(fits + 10.0 ** (int(np.floor(np.log10(fits))) - 1), 12))
    return (f"the survey spans {span[0]:.0f} x {span[1]:.0f} m: {cells} cells of "
            f"dem.resolution {res:g} m, over dem.max_cells = {limit}; raise it to {cells} "
            f"(~{_CELL_BYTES} bytes a cell: {cells * _CELL_BYTES / 1e9:.2g} GB) or coarsen "
            f"dem.resolution to {fits:g} m")


class _Cells:
    """Per-cell sums of a grid window: count, sum of z and of x, y offsets from the
    cell centre, plus the interpolated layer. ``origin_ij`` is the global integer index
    of cell (0, 0) (origin = origin_ij * resolution, so windows always line up)."""

    def __init__(self, origin_ij: np.ndarray, shape: tuple[int, int], res: float):
        self.origin_ij = np.asarray(origin_ij, dtype=np.int64)
        self.shape = shape
        self.res = res
        self.count = np.zeros(shape, np.uint32)
        self.sums = np.zeros((3,) + shape, np.float64)  # z, dx, dy
        self.fill = np.full(shape, np.nan, np.float32)

    def reframe(self, origin_ij: np.ndarray, shape: tuple[int, int]) -> None:
        """Move/resize the window, keeping the cells both windows share."""
        origin_ij = np.asarray(origin_ij, dtype=np.int64)
        if np.array_equal(origin_ij, self.origin_ij) and shape == self.shape:
            return
        old = (self.count, self.sums, self.fill)
        old_ij, old_shape = self.origin_ij, self.shape
        self.__init__(origin_ij, shape, self.res)  # type: ignore[misc]
        # overlap in global (col, row) indices
        lo = np.maximum(old_ij, origin_ij)
        hi = np.minimum(old_ij + np.array(old_shape[::-1]), origin_ij + np.array(shape[::-1]))
        if np.any(hi <= lo):
            return
        src = (slice(lo[1] - old_ij[1], hi[1] - old_ij[1]),
               slice(lo[0] - old_ij[0], hi[0] - old_ij[0]))
        dst = (slice(lo[1] - origin_ij[1], hi[1] - origin_ij[1]),
               slice(lo[0] - origin_ij[0], hi[0] - origin_ij[0]))
        self.count[dst] = old[0][src]
        self.sums[(slice(None),) + dst] = old[1][(slice(None),) + src]
        self.fill[dst] = old[2][src]

    def add(self, xyz: np.ndarray) -> tuple[slice, slice] | None:
        """Accumulate points xyz (N, 3) float64 metres; return the (rows, cols) bounding
        slices of the touched cells (None when no point falls in the window).

        Counted by one bincount over the touched cells' bounding box: a message covers a
        small part of the window, and sorting its points (np.unique) cost 4 x as much."""
        rows, cols = self.shape
        # global cell index first, then local: the offsets below are from the same centres
        gc = np.floor(xyz[:, 0] / self.res).astype(np.int64)
        gr = np.floor(xyz[:, 1] / self.res).astype(np.int64)
        c, r = gc - self.origin_ij[0], gr - self.origin_ij[1]
        ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
        if not ok.all():
            if not ok.any():
                return None
            xyz, gc, gr, c, r = xyz[ok], gc[ok], gr[ok], c[ok], r[ok]
        r0, r1, c0, c1 = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
        box = (r - r0) * (c1 - c0) + (c - c0)
        size, region = (r1 - r0) * (c1 - c0), (slice(r0, r1), slice(c0, c1))
        self.count[region] += np.bincount(box, minlength=size).reshape(
            r1 - r0, c1 - c0).astype(np.uint32)
        for layer, values in enumerate((xyz[:, 2], xyz[:, 0] - (gc + 0.5) * self.res,
                                        xyz[:, 1] - (gr + 0.5) * self.res)):
            self.sums[(layer,) + region] += np.bincount(box, weights=values,
                                                        minlength=size).reshape(r1 - r0, c1 - c0)
        return region

    def refill(self, region: tuple[slice, slice], *, cfg: DemBuilderConfig,
               variograms: _VariogramCache | None = None) -> None:
        """Re-interpolate the empty cells of ``region`` lying within fill_distance of a
        measured cell, from the measured cells up to 2 fill distances around the region.
        ``variograms``: where kriging takes its variogram from (None: fitted here)."""
        rows, cols = self.shape
        reach = int(np.ceil(cfg.dem.fill_distance / self.res))
        r0, r1 = max(region[0].start - reach, 0), min(region[0].stop + reach, rows)
        c0, c1 = max(region[1].start - reach, 0), min(region[1].stop + reach, cols)
        s0, s1 = max(r0 - reach, 0), min(r1 + reach, rows)
        t0, t1 = max(c0 - reach, 0), min(c1 + reach, cols)
        self.fill[r0:r1, c0:c1] = np.nan
        count = self.count[s0:s1, t0:t1]
        measured = count > 0
        if not measured.any() or reach == 0:
            return
        inner = (slice(r0 - s0, r1 - s0), slice(c0 - t0, c1 - t0))
        dist = ndimage.distance_transform_edt(~measured)[inner] * self.res
        target = (dist > 0) & (dist <= cfg.dem.fill_distance)
        if not target.any():
            return
        if cfg.dem.interpolation == "tin":
            # A triangle over an empty cell has its corners on the rim of the gap (its
            # circumcircle holds no sample, which a dense measured patch would), so the
            # measured cells within 3 cells of an empty one triangulate the gaps as all
            # of them would, at a fraction of the Delaunay cost.
            measured = measured & (ndimage.distance_transform_edt(measured) <= 3.0)
        mr, mc = np.nonzero(measured)
        n = count[mr, mc].astype(np.float64)
        sums = self.sums[:, s0:s1, t0:t1][:, mr, mc] / n
        sx = (self.origin_ij[0] + t0 + mc + 0.5) * self.res + sums[1]
        sy = (self.origin_ij[1] + s0 + mr + 0.5) * self.res + sums[2]
        tr, tc = np.nonzero(target)
        qx = (self.origin_ij[0] + c0 + tc + 0.5) * self.res
        qy = (self.origin_ij[1] + r0 + tr + 0.5) * self.res
        samples = np.column_stack([sx, sy])
        vg = (variograms.get(samples, sums[0], cfg.kriging)
              if variograms is not None and cfg.dem.interpolation == "kriging" else None)
        values = interpolate(cfg.dem.interpolation, samples, sums[0],
                             np.column_stack([qx, qy]), kriging_cfg=cfg.kriging,
                             rbf_cfg=cfg.rbf, rbfnn_cfg=cfg.rbfnn,
                             idw_neighbours=cfg.dem.idw_neighbours, idw_power=cfg.dem.idw_power,
                             rng=INTERPOLATION_SEED, variogram=vg)
        self.fill[r0 + tr, c0 + tc] = values.astype(np.float32)

    def grid(self, reason: str = "") -> DemGrid:
        measured = self.count > 0
        mean = np.divide(self.sums[0], self.count, out=np.zeros(self.shape),
                         where=measured).astype(np.float32)
        elevation = np.where(measured, mean, self.fill).astype(np.float32)
        interpolated = (~measured & np.isfinite(self.fill)).astype(np.uint8)
        if not reason and not measured.any():
            reason = "no ground points in the grid"
        return DemGrid(elevation, interpolated, self.count.copy(),
                       self.origin_ij.astype(np.float64) * self.res, self.res, reason)


def _flat_reason(xyz: np.ndarray) -> str:
    if len(xyz) == 0:
        return "no ground points"
    # Points spanning a plane are >= 3 distinct ones; only a degenerate set pays for the
    # merge that counts its distinct points.
    reason = degeneracy(xyz[:, :2]) and degeneracy(merge_coincident(xyz[:, :2], xyz[:, 2])[0])
    if reason:
        return reason + ": measured cells only, nothing interpolated"
    if np.ptp(xyz[:, 2]) == 0:
        return "all ground points at one height: a flat DEM"
    return ""


def build_dem(ground_xyz: np.ndarray, *, cfg: DemBuilderConfig,
              bounds: tuple[float, float, float, float] | None = None) -> DemGrid:
    """Whole-survey DEM of ground points (N, 3) float64 metres.

    The grid covers ``bounds`` (xmin, ymin, xmax, ymax metres; default the points'
    bounding box), origin aligned to multiples of ``cfg.dem.resolution``, so two DEMs
    built with the same bounds share their grid cell for cell. Raises ConfigError when it
    would exceed ``cfg.dem.max_cells``. Degenerate input (no points, < 3 distinct,
    collinear) gives an empty or measured-only DEM with ``reason`` set, never an
    exception from Qhull.
    """
    xyz = points_xyz(ground_xyz, "build_dem: ground_xyz", nonfinite="drop")
    res = cfg.dem.resolution
    if len(xyz) == 0 and bounds is None:
        return empty_grid(res, "no ground points")
    box = (np.array(bounds, dtype=np.float64).reshape(2, 2) if bounds is not None
           else np.stack([column_min(xyz[:, :2]), column_max(xyz[:, :2])]))
    lo, hi = np.floor(box[0] / res), np.floor(box[1] / res)
    cols, rows = hi - lo + 1  # floats: a box of 1e19 cells overflows int64
    if rows * cols > cfg.dem.max_cells:
        raise ConfigError(f"DEM of {rows:.6g} x {cols:.6g} cells exceeds dem.max_cells = "
                          f"{cfg.dem.max_cells}; raise it or coarsen dem.resolution")
    rows, cols = int(rows), int(cols)  # (region bounds below: slices take integers only)
    cells = _Cells(lo.astype(np.int64), (rows, cols), res)
    if len(xyz):
        cells.add(xyz)
    reason = _flat_reason(xyz)
    if not reason.endswith("nothing interpolated"):
        cells.refill((slice(0, rows), slice(0, cols)), cfg=cfg)
    return cells.grid(reason)


class RollingDem:
    """DEM accumulated across messages, bounded in memory.

    ``dem.extent`` > 0: a square window of that size follows the vehicle (or the centre
    of the latest ground when no vehicle position is given); cells leaving it are
    forgotten. ``dem.extent`` = 0: the grid grows to cover the whole flight, at most
    ``dem.max_cells`` cells (beyond that it becomes a window of that many cells around
    the latest data), unless `whole`: then a grid that would exceed it raises
    ConfigError (`export-dem`, whose DEM is of the whole survey: a window lost the
    survey's first part without a word). Each update adds the points to their cells' sums
    (measured cells become the mean of all ground seen there); the empty cells near the
    data added since are re-interpolated when the DEM is read (``snapshot``) or on
    ``refill``.
    """

    def __init__(self, cfg: DemBuilderConfig, *, whole: bool = False):
        self.cfg = cfg
        self.whole = whole
        self._res = cfg.dem.resolution
        side = max(int(np.floor(np.sqrt(cfg.dem.max_cells))), 1)
        if cfg.dem.extent > 0:
            side = min(side, max(int(np.ceil(cfg.dem.extent / self._res)), 1))
        self._side = side  # window edge in cells
        self._cells: _Cells | None = None
        self._variograms = _VariogramCache()
        self.stamp: float | None = None
        # Global (row0, row1, col0, col1) cell bounds touched since the last refill. The
        # empty cells are filled when the DEM is read (published at `dem.publish_rate`,
        # saved), not on every message: the node publishes at 1 Hz and clouds come at
        # 10 Hz, so filling per message did ten times the interpolation anyone saw.
        self._dirty: tuple[int, int, int, int] | None = None

    def _window(self, xyz: np.ndarray, vehicle_xy: np.ndarray | None
                ) -> tuple[np.ndarray, tuple[int, int]]:
        centre = (np.asarray(vehicle_xy, dtype=np.float64).reshape(2) if vehicle_xy is not None
                  else xyz[:, :2].mean(axis=0))
        origin = np.floor(centre / self._res).astype(np.int64) - self._side // 2
        return origin, (self._side, self._side)

    def _frame(self, xyz: np.ndarray, vehicle_xy: np.ndarray | None) -> _Cells:
        """Place the window for this message; return the cells."""
        res = self._res
        if self.cfg.dem.extent > 0:
            origin, shape = self._window(xyz, vehicle_xy)
        else:
            lo = np.floor(column_min(xyz[:, :2]) / res).astype(np.int64)
            hi = np.floor(column_max(xyz[:, :2]) / res).astype(np.int64) + 1
            if self._cells is not None:
                old_lo = self._cells.origin_ij
                old_hi = old_lo + np.array(self._cells.shape[::-1])
                if np.all(lo >= old_lo) and np.all(hi <= old_hi):
                    return self._cells
                lo, hi = np.minimum(lo, old_lo), np.maximum(hi, old_hi)
            # grow in steps of 64 cells so a growing flight does not copy every message
            # (the exact size where the steps alone would pass dem.max_cells)
            size = -(-(hi - lo) // 64) * 64
            if size[0] * size[1] > self.cfg.dem.max_cells:
                size = hi - lo
            if size[0] * size[1] > self.cfg.dem.max_cells and self.whole:
                raise DemTooLarge("the ground spans more than dem.max_cells")
            if size[0] * size[1] > self.cfg.dem.max_cells:
                origin, shape = self._window(xyz, vehicle_xy)
            else:
                origin, shape = lo, (int(size[1]), int(size[0]))
        if self._cells is None:
            self._cells = _Cells(origin, shape, res)
        else:
            self._cells.reframe(origin, shape)
        return self._cells

    def update(self, ground_xyz: np.ndarray, vehicle_xy: np.ndarray | None = None,
               stamp: float | None = None) -> None:
        """Add ground points (N, 3) float64 metres; vehicle_xy (2,) metres or None;
        stamp: the message time in seconds (kept as ``self.stamp``)."""
        xyz = points_xyz(ground_xyz, "DEM update: ground_xyz", nonfinite="drop")
        if stamp is not None:
            self.stamp = float(stamp)
        if len(xyz) == 0:
            return
        cells = self._frame(xyz, vehicle_xy)
        region = cells.add(xyz)
        if region is not None:
            oi, oj = int(cells.origin_ij[1]), int(cells.origin_ij[0])
            box = (region[0].start + oi, region[0].stop + oi,
                   region[1].start + oj, region[1].stop + oj)
            d = self._dirty
            self._dirty = box if d is None else (min(d[0], box[0]), max(d[1], box[1]),
                                                 min(d[2], box[2]), max(d[3], box[3]))

    def refill(self) -> None:
        """Interpolate the empty cells near the data added since the last refill."""
        if self._cells is None or self._dirty is None:
            return
        cells, (r0, r1, c0, c1) = self._cells, self._dirty
        self._dirty = None
        oi, oj = int(cells.origin_ij[1]), int(cells.origin_ij[0])
        rows, cols = cells.shape
        r0, r1 = max(r0 - oi, 0), min(r1 - oi, rows)
        c0, c1 = max(c0 - oj, 0), min(c1 - oj, cols)
        if r1 > r0 and c1 > c0:
            cells.refill((slice(r0, r1), slice(c0, c1)), cfg=self.cfg,
                         variograms=self._variograms)

    def snapshot(self) -> DemGrid:
        """The current DEM (a frozen copy), its empty cells near new data filled first."""
        if self._cells is None:
            return empty_grid(self._res, "no ground received yet")
        self.refill()
        return self._cells.grid()
