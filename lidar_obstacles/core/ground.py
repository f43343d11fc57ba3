"""Ground filtering: progressive TIN densification, per-tile RANSAC planes, and the hybrid.

- ``tin`` — Axelsson (2000), the TerraScan filter of seed 004: seeds are the lowest point
  per `tin.cell_size` cell; a TIN of the ground so far; every other point inside a facet
  joins when its distance d to the facet's plane is below `tin.max_distance` and the
  angles asin(d / S) to the three vertices are below `tin.max_angle`. Batches per round
  (the best candidate of each facet, so the TIN never jumps past a point it should have
  judged first), until no point joins.
- ``ransac`` — the paper's PCL segmentation: per XY tile a RANSAC plane with the robust
  eigenvalue fit; its inliers are ground. Tiles whose fit is poor are split in four and
  re-run (the paper re-tiled its blocks 15 and 24 by hand).
- ``hybrid`` (default) — a raster progressive morphological filter (Pingel et al. 2013,
  SMRF) on the grid of lowest points, with low blunders removed first; the ground cells'
  surface is in-painted, points within a slope-dependent band of it are ground, and the
  surface is rebuilt from them until the labels repeat (at most 8 rounds: the rebuilds give
  back the convex terrain the opening cuts, ridge crests and terrace rims). Beyond SMRF
  (the steps of `morphological_ground`, their constants in `HybridSettings`):
  - on ground steeper than 0.8 only the opening's first 6 m of window count: narrow
    terraces, embankment tops and spurs are not buildings;
  - the object cells are those of a second opening, of the surface minus its 24 m median
    trend: on a hillside terrace edges and spurs stand out of the plain opening, not of
    the de-trended one, where a building stands out of both;
  - after the last round, rejected points on the rim of a plateau of ground points (a
    smooth, gentle half-disc whose plane passes through the point, a drop of more than
    2 m beside it) join the ground, and on sparse scans so do points on the face of a
    cliff (ground above and below them within 5 m, rising faster than 2:1), then the rims
    near those once more;
  - on sparse scans, ground points more than 0.15 m above all ground of the other cells
    within 5 m (single bush and hedge points the band let in) leave the ground, twice;
  - on dense scans (>= 4 ground points per m^2) the flat-ground band narrows from 0.5 to
    0.15 m, and pieces of ground raised more than 2 m above the ground beside them with
    nothing higher around them (roofs a strip caught at its edge or beside their own
    shadow, which no window of the opening could cut off) leave the ground after the
    rounds, as do pits of a few cells (stray low points).
  It is O(N) and raster-only, many times faster than TIN densification (which rebuilds a
  Delaunay per round) and more accurate on the ISPRS samples with one parameter set
  (benchmarks/bench_ground.py). How each step and constant was chosen, what was measured
  and rejected, and how the filter got its speed: docs/measurements.md, "Ground filter:
  how the hybrid got here".

Height above ground of every point comes from the ground surface, never from a sensor
height: for `hybrid` the in-painted raster of the ground points, read bilinearly; for `tin`
and `ransac` the TIN of the ground points (the nearest ground point outside its hull).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from lidar_obstacles.config import GroundConfig, RansacConfig, TilingConfig, TinConfig
from lidar_obstacles.core.arrays import (all_columns, cell_index, column_max, column_min,
                                         sparse_grid_cell,
                                         lowest_per_cell, points_xyz, snap_micrometres,
                                         tree_query)
from lidar_obstacles.core.ransac import ransac_plane
from lidar_obstacles.errors import CloudFormatError

# TIN variant: a seed this far below the plane of its neighbouring seeds is a low blunder.
LOW_SEED_DROP = 2.0  # m
HIGH_SEED_DROP = 5.0  # m: a seed this far above its neighbours is an object's lowest point
# Axelsson's vertex angles asin(d / S) are judged with S at least this far (m): next to a
# vertex S is tiny and the angle meaningless (a ground point 0.3 m from an accepted one
# and 0.12 m off the facet's plane is at 23 degrees), so real ground there never joined
# (ISPRS samp22: 56 % of the ground left out failed the angles alone, with d < 1 m).
ANGLE_MIN_REACH = 2.0  # m
# Rounds of the raster filter's low-blunder test (morphological_ground), each without the
# blunders found before: the simulator's echoes come in clusters of 2-3.
LOW_ROUNDS = 3


@dataclass(frozen=True)
class HybridSettings:
    """Raster filter settings (SMRF's, slope 0.2 measured best on ISPRS; no per-site tuning).

    The first four are the `ground.*` parameters (their defaults the schema's); the rest
    are the method's constants, fields so that tests and docs/figures.py can turn a test
    off (0) and show what it does. What each was measured against and the values tried:
    docs/measurements.md, "Ground filter: how the hybrid got here".
    """

    cell: float = GroundConfig.cell  # m
    slope: float = GroundConfig.slope  # rise over run that opening may remove per window step
    window: float = GroundConfig.window  # m, largest opening radius (~half the largest building)
    fine_window: float = 6.0  # m: opening radii grow by one cell up to here, then by two
    threshold: float = GroundConfig.threshold  # m, acceptance around ground on flat ground
    scalar: float = 1.25  # extra acceptance per unit of local slope
    low_outlier: float = 2.0  # m below the lowest neighbouring cells: a blunder
    low_window: int = 7  # cells, the neighbourhood of the low-blunder test
    # Where that window holds no other ground (see _lone_low_cells), a point more than
    # `low_outlier` plus `lone_slope` times the distance below the nearest ground within
    # `lone_reach` is a blunder too: a noise echo beyond a strip's edge, which sank a bubble
    # of the rolling DEM 20 m wide and 5-15 m deep. Judged on the first labels' ground (on
    # every cell's lowest point, a street seen alone between roofs has only roofs nearest),
    # in pieces of up to `lone_cells` (echoes of one strip a few metres apart). A lone real
    # ground point on terrain falling faster than lone_slope beyond a strip's edge is lost:
    # one point, where a kept echo sinks the DEM around it.
    lone_reach: float = 30.0  # m, how far the cells judging a lone one are sought; 0: off
    lone_slope: float = 0.05  # rise over run the ground may fall towards a lone cell
    lone_cells: int = 4  # cells of a piece judged as lone at most
    # Where the ground surface after the opening is steeper than `steep_slope`, only the
    # flags of the opening steps up to `steep_window` count (the same run, no extra
    # opening): large windows cut narrow terraces, embankments and spurs there.
    steep_window: float = 6.0  # m
    steep_slope: float = 0.8  # rise over run of the ground surface
    # Label / rebuild-surface rounds, at most; they stop early once the labels repeat.
    passes: int = 8
    # Dense scans (AHN: 10-60 points per m^2): the lowest ground point of a 1 m cell lies
    # within the noise of the ground, so the band above it need not cover interpolation
    # across empty cells, and low objects 0.15-0.35 m high (class 1 in the corridor tiles)
    # fall outside it. The flat-ground threshold narrows from `threshold` to
    # `dense_threshold` as the ground points of the first labels, per m^2 over the 3 x 3
    # cells around a point, go from `dense_from` to `dense_full`. ISPRS (about 1 ground
    # point per m^2) keeps its labels.
    dense_threshold: float = 0.15  # m
    dense_from: float = 4.0  # ground points per m^2
    dense_full: float = 10.0  # ground points per m^2
    # The object cells are those of a second opening, of the first surface minus its
    # large-scale trend: the median over `trend_window` metres (an odd number of blocks)
    # of the ground surface after the first opening, on medians of `trend_block` x
    # `trend_block` cells, bilinear back to the cells. On a hillside the plain opening
    # takes terrace edges and spurs for objects, the de-trended one does not; a building
    # stands out in both. The first opening only finds the surface the trend is taken
    # from (and, with the second, the steep-window flags, `_steep_objects`). The trend is
    # of the ground surface, not of the lowest points, which buildings raise.
    trend_window: float = 24.0  # m; 0: no second opening
    trend_block: int = 8  # cells
    # Rims of terrace steps and cliffs (see _rim_points): after the last round, a rejected
    # point joins the ground when the real ground points in a half-disc beside it form a
    # smooth, gentle, two-dimensional plateau whose plane passes through it, and ground
    # lies more than `rim_drop` below it within `rim_window` (the step). No surface
    # rebuild between passes (each rebuild and band test cost more than the test itself).
    rim_window: float = 6.0  # m; 0: no rim test (and no peak test)
    rim_drop: float = 2.0  # m
    rim_band: float = 0.5  # m, above the plateau's plane
    rim_below: float = 1.5  # m, below it (rounded convex edges)
    rim_neighbours: int = 16
    rim_directions: int = 8
    rim_max_slope: float = 1.0  # rise over run of the plateau
    rim_max_rms: float = 0.3  # m
    rim_spread: float = 1.0  # m
    rim_near: float = 4.0  # m
    # Rim passes: the second judges only the rejected points near what the first pass and
    # the face test (below) gave back, whose rims the new ground can now carry.
    rim_passes: int = 2
    # Faces of cliffs and terrace walls (see _face_points), after each rim pass but the
    # last: a rejected point with ground more than `face_rise` above and below it among
    # its `face_neighbours` nearest ground points within `face_radius`, an upper and a
    # lower one of them rising faster than `face_steep` (rise over run) from one to the
    # other. The steepness, not a straight segment through the point: cliff faces are not
    # straight at 2.4 m spacing.
    face_radius: float = 5.0  # m; 0: no face test
    face_rise: float = 1.0  # m
    face_steep: float = 2.0  # rise over run between the upper and the lower ground point
    face_neighbours: int = 12
    # Peaks (see _peak_points), after the rims and faces, on sparse scans only: a ground
    # point more than `peak_rise` above every ground point of the other cells within
    # `peak_window` (a square) leaves the ground, `peak_passes` times (the second pass
    # takes what the first uncovered: two-point bushes).
    peak_window: float = 5.0  # m; 0: no peak test
    peak_rise: float = 0.15  # m
    peak_passes: int = 2
    # Raised islands (see _islands_and_pits), after the label rounds, on dense scans only: a
    # piece of ground with ground of other pieces more than `island_rise` lower beside it
    # and none more than that higher is a roof the opening could not cut off (its own
    # higher cells do not count: a roof pitched at 40 degrees or more rises 2 m within the
    # reach). The walls under an island's edges, in the band of the surface across the
    # roof, leave with it when the surface without it puts them outside the band. A UAV
    # strip often catches a roof at its edge, or beside the building's own shadow, so that
    # no window of the opening holds ground on every side, and the rounds then spread the
    # roof's ground across it. Stray low points the blunder test missed (two that shield
    # each other) are lower ground too: counted, they made the whole strip an island, hence
    # `island_min_cells` and `island_pit_share`. Not on sparse scans (ISPRS: most 1 m cells
    # empty, ground pieces not connected; its total error 3.52 -> 4.82 %).
    island_rise: float = 2.0  # m; 0: no island test
    island_connect: float = 1.0  # m, the largest step between neighbouring cells of a piece
    island_reach: float = 3.0  # m, how far beside a piece lower or higher ground is sought
    island_extent: float = 50.0  # m: a wider raised piece is a plateau (a quarry's rim)
    island_pit_share: float = 0.8  # of a window higher ground around a pit
    island_min_cells: int = 2  # the smallest piece of lower ground that counts
    # Pits of up to `pit_cells` cells leave the ground too (their points within
    # island_rise of the pit's floor).
    pit_cells: int = 4
    # Where the raster's cells fall: its corner lies `anchor` (x, y) cells, 0 to 1, before
    # the lowest x and y of the points. Not a setting: a measure of how much the labels
    # owe to the grid's placement (benchmarks/bench_ground.py, "grid placements").
    anchor: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class GroundResult:
    """ground: (N,) bool; height_above_ground: (N,) float32 m (NaN when no surface);
    tiles: tiles processed; splits: tiles split again for a poor fit; timings: seconds."""

    ground: np.ndarray
    height_above_ground: np.ndarray
    tiles: int = 1
    splits: int = 0
    timings: dict[str, float] = field(default_factory=dict)


def _drop_odd_seeds(seeds_xyz: np.ndarray) -> np.ndarray:
    """(S,) bool over seeds (S, 3) m: those neither far below the least-squares plane of
    their 8 nearest seeds (a low blunder) nor far above it (a cell holding only an object,
    e.g. a wire at the edge). The plane, not the neighbours' median: on a slope the median
    of an edge seed's neighbours (all uphill, or all down) lies a cell's rise away, and
    a 17 degree hillside lost its first and last rows of seeds."""
    if len(seeds_xyz) < 5:
        return np.ones(len(seeds_xyz), bool)
    k = min(9, len(seeds_xyz))
    _, nn = cKDTree(seeds_xyz[:, :2]).query(seeds_xyz[:, :2], k=k)
    rel = seeds_xyz[nn[:, 1:]] - seeds_xyz[:, None, :]  # (S, k-1, 3) around each seed
    design = np.concatenate([rel[:, :, :2], np.ones(rel.shape[:2] + (1,))], axis=2)
    normal = np.einsum("ski,skj->sij", design, design) + 1e-9 * np.eye(3)
    rhs = np.einsum("ski,sk->si", design, rel[:, :, 2])
    # the plane z = a x + b y + c through the neighbours, relative to the seed: c is the
    # plane's height over the seed, so the seed stands -c above the plane
    above = -np.linalg.solve(normal, rhs[..., None])[:, 2, 0]
    return (above > -LOW_SEED_DROP) & (above < HIGH_SEED_DROP)


def _box_seeds(xy: np.ndarray, seeds_xyz: np.ndarray, spacing: float) -> np.ndarray:
    """(B, 3) m: virtual seeds every `spacing` m (at most) round the box of xy (N, 2) m,
    1 m outside it, each at the height of the nearest real seed of seeds_xyz (S, 3) m, so
    that the TIN covers every point. Without them the seeds' hull left the points outside
    it unjudged: the lowest point of a cell on a slope lies at its downhill edge, so the
    top row of cells (a quarter of an 80 m square at 20 m cells) never became ground."""
    lo, hi = column_min(xy) - 1.0, column_max(xy) + 1.0
    nx, ny = (np.ceil((hi - lo) / spacing).astype(np.int64) + 1).tolist()
    ex, ey = np.linspace(lo[0], hi[0], max(nx, 2)), np.linspace(lo[1], hi[1], max(ny, 2))
    ring = np.concatenate([np.column_stack([ex, np.full(len(ex), lo[1])]),
                           np.column_stack([ex, np.full(len(ex), hi[1])]),
                           np.column_stack([np.full(len(ey) - 2, lo[0]), ey[1:-1]]),
                           np.column_stack([np.full(len(ey) - 2, hi[0]), ey[1:-1]])])
    _, nearest = cKDTree(seeds_xyz[:, :2]).query(ring)
    return np.column_stack([ring, seeds_xyz[nearest, 2]])


def _facet_test(tri: Delaunay, ground_xyz: np.ndarray, pts: np.ndarray, simplex: np.ndarray,
                max_distance: float, max_angle_deg: float, min_edge: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool accepted and (M,) distance (m) to the facet's plane, of points pts (M, 3) m
    inside facets `simplex` (M,) of the TIN of ground_xyz (G, 3) m: within max_distance of
    the facet's plane, and at most max_angle_deg from it seen from each vertex (asin(d / S),
    S at least ANGLE_MIN_REACH). A facet whose longest horizontal edge is below `min_edge`
    m is dense enough and takes no more points."""
    v = ground_xyz[tri.simplices[simplex]]  # (M, 3 vertices, 3)
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(normal, axis=1)
    norm[norm == 0] = np.inf
    d = np.abs(np.einsum("ij,ij->i", normal, pts - v[:, 0])) / norm
    s = np.linalg.norm(v - pts[:, None, :], axis=2)  # distances to the three vertices
    sin_max = np.sin(np.radians(max_angle_deg))
    ok = (d < max_distance) & np.all(d[:, None] < sin_max * np.maximum(s, ANGLE_MIN_REACH),
                                     axis=1)
    if min_edge > 0:
        edges = v[:, [1, 2, 0], :2] - v[:, :, :2]  # (M, 3 edges, 2)
        ok &= np.einsum("mei,mei->me", edges, edges).max(axis=1) >= min_edge * min_edge
    return ok, d


def _locate(tri: Delaunay, xy: np.ndarray, max_steps: int = 64) -> np.ndarray:
    """(M,) the facet of `tri` holding each point of xy (M, 2) m, -1 outside.

    A walk for all points at once: from a facet of the point's nearest vertex, step to the
    neighbour across the edge the point lies beyond, until the point is inside (most take
    0-2 steps). Not Qhull's own walk: on a dense TIN it often fails on slivers and falls
    back to trying every facet (most of the time of a 20 000-point slope). A point on an
    edge gets the facet its walk meets first; a point still walking after `max_steps` is
    left to Qhull."""
    out = np.full(len(xy), -1, np.int64)
    if len(xy) == 0 or len(tri.simplices) == 0:
        return out
    used = np.unique(tri.simplices)  # not the duplicates Qhull left out
    _, nearest = cKDTree(tri.points[used]).query(xy)
    facet = tri.vertex_to_simplex[used[nearest]].astype(np.int64)
    walking = np.arange(len(xy))
    eps = 1e-10
    for _ in range(max_steps):
        v = tri.points[tri.simplices[facet]]  # (W, 3, 2)
        e0, e1, d = v[:, 0] - v[:, 2], v[:, 1] - v[:, 2], xy[walking] - v[:, 2]
        det = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero-area sliver: Qhull's
            b0 = (d[:, 0] * e1[:, 1] - d[:, 1] * e1[:, 0]) / det
            b1 = (e0[:, 0] * d[:, 1] - e0[:, 1] * d[:, 0]) / det
        bary = np.column_stack([b0, b1, 1.0 - b0 - b1])
        inside = np.all(bary >= -eps, axis=1)
        out[walking[inside]] = facet[inside]
        step = ~inside & (det != 0)
        across = tri.neighbors[facet[step], np.argmin(bary[step], axis=1)]
        beyond = across >= 0  # else outside the TIN: -1
        walking, facet = walking[step][beyond], across[beyond].astype(np.int64)
        if len(walking) == 0:
            break
    lost = np.concatenate([walking, np.flatnonzero(out < 0)])  # slivers, long walks
    if len(lost):
        lost = np.unique(lost)
        out[lost] = tri.find_simplex(xy[lost])
    return out


def tin_densification(xyz: np.ndarray, cfg: TinConfig, *, fixed: np.ndarray | None = None,
                      drop_odd_seeds: bool = False) -> np.ndarray:
    """(N,) bool ground by progressive TIN densification of (N, 3) centred points.

    Axelsson (2000): the lowest point per `cfg.cell_size` cell seeds a TIN; each round, the
    points inside a facet that pass its distance and vertex-angle tests, the closest to its
    plane of each facet, join the ground (a batch per round), and the TIN is rebuilt,
    until no point joins or `cfg.max_iterations` rounds. Made better: virtual seeds round the box
    (`_box_seeds`), odd seeds judged against their neighbours' plane (`_drop_odd_seeds`,
    with drop_odd_seeds) and the vertex angles judged from ANGLE_MIN_REACH at least (the
    figures: docs/measurements.md, "Ground filter: how the hybrid got here"). Most of its
    time is Qhull's triangulation, one a round.

    fixed: (F, 3) extra ground points (the streaming context), part of the TIN, not output.
    """
    n = len(xyz)
    ground = np.zeros(n, bool)
    if n == 0:
        return ground
    seeds = lowest_per_cell(xyz, column_min(xyz[:, :2]), cfg.cell_size)
    if drop_odd_seeds:
        seeds = seeds[_drop_odd_seeds(xyz[seeds])]
    ground[seeds] = True
    fixed = np.zeros((0, 3)) if fixed is None else fixed
    if len(seeds):
        fixed = np.concatenate([fixed, _box_seeds(xyz[:, :2], xyz[seeds], cfg.cell_size)])
    cand = np.flatnonzero(~ground)
    for _ in range(cfg.max_iterations):
        g_xyz = np.concatenate([fixed, xyz[ground]])
        if len(g_xyz) < 3 or len(cand) == 0:
            break
        try:
            tri = Delaunay(g_xyz[:, :2])
        except QhullError:
            break  # collinear or coincident ground: nothing more to densify
        simplex = _locate(tri, xyz[cand, :2])
        at = np.flatnonzero(simplex >= 0)  # into cand
        ok, d = _facet_test(tri, g_xyz, xyz[cand[at]], simplex[at], cfg.max_distance,
                            cfg.max_angle, cfg.min_edge)
        at, facet, d = at[ok], simplex[at[ok]], d[ok]
        if len(at) == 0:
            break
        # One point per facet and round, the closest to the facet's plane: the rounds are
        # the batches, and a facet's next point is judged on the facets it made.
        order = np.lexsort((d, facet))
        first = np.ones(len(order), bool)
        first[1:] = facet[order[1:]] != facet[order[:-1]]
        joined = at[order[first]]
        ground[cand[joined]] = True
        cand = np.delete(cand, joined)
    return ground


def _relax(pad: np.ndarray, avg: np.ndarray, quarter: np.ndarray, known: np.ndarray,
           rounds: int) -> None:
    """`rounds` of 4-neighbour averaging of the missing cells of the (rows, cols) grid held
    inside `pad` ((rows + 2, cols + 2), its border repeating the edge cells); the known
    cells are never changed. quarter: (rows, cols) 0.25 where missing, 0 where known;
    known: the known values, 0 where missing; avg: (rows, cols) scratch.

    The update is avg x quarter + known, exact (x + 0 and x x 1 are exact) and without a
    mask: a masked write over scattered holes (sparse scans leave every other cell empty)
    costs 20-100 x more, in branch mispredictions, than a plain pass.
    """
    out = pad[1:-1, 1:-1]
    for _ in range(rounds):
        pad[0, 1:-1], pad[-1, 1:-1] = pad[1, 1:-1], pad[-2, 1:-1]
        pad[1:-1, 0], pad[1:-1, -1] = pad[1:-1, 1], pad[1:-1, -2]
        np.add(pad[:-2, 1:-1], pad[2:, 1:-1], out=avg)
        avg += pad[1:-1, :-2]
        avg += pad[1:-1, 2:]
        avg *= quarter
        np.add(avg, known, out=out)


class _Inpainter:
    """In-painting of (rows, cols) grids of one shape, its pyramid's arrays kept and reused.

    Why: a fresh grid-sized float64 array costs about as much in page faults (~1 us per
    4 KB page on the 2-core test machine) as ten passes of arithmetic over it, and the
    hybrid filter in-paints the same grid shape up to 12 times per cloud.

    The pyramid is float32: its passes are memory-bound, and half the bytes cost the
    hybrid filter ~13 % less CPU with the same labels. The known cells come back exact; a
    filled cell is good to ~1e-7 of the grid's values (the filter's are centred:
    micrometres).
    """

    def __init__(self, shape: tuple[int, int]) -> None:
        self._levels: list[dict[str, np.ndarray]] = []
        self._result = np.empty(shape)

    def _level(self, k: int, shape: tuple[int, int]) -> dict[str, np.ndarray]:
        """Arrays of pyramid level k: `z` (values, 0 in the holes) and `known` zero-padded
        to even sizes (for the 2 x 2 sums), `pad` the level's filled values with a
        one-cell border (for `_relax`), `avg`, `quarter` and `miss` (rows, cols)."""
        if k < len(self._levels):
            return self._levels[k]
        h, w = shape
        even = (h + h % 2, w + w % 2)
        f = np.float32
        lv = {"z": np.zeros(even, f), "known": np.zeros(even, bool),
              "pad": np.empty((h + 2, w + 2), f), "avg": np.empty(shape, f),
              "quarter": np.empty(shape, f), "miss": np.empty(shape, bool)}
        self._levels.append(lv)
        return lv

    def __call__(self, grid: np.ndarray, smoothing: int = 4) -> np.ndarray:
        """Fill the NaN (or infinite) cells of (rows, cols) `grid` (see `inpaint`). Returns
        `grid` itself when it has no hole or no known cell, else an array of this object
        that the next call overwrites."""
        grid = np.ascontiguousarray(grid, dtype=np.float64)
        known = np.isfinite(grid)
        if known.all() or not known.any():
            return grid
        h, w = grid.shape
        lv = self._level(0, (h, w))
        np.logical_not(known, out=lv["miss"])
        np.logical_not(lv["miss"], out=lv["known"][:h, :w])
        # The holes' bits cleared (an AND with 0 or all ones): no masked write, which
        # costs 20-100 x more on scattered holes (see _relax). The exact values into the
        # result, float32 ones into the pyramid.
        np.bitwise_and(grid.view(np.int64), np.negative(known.view(np.int8)),
                       out=self._result.view(np.int64))
        np.copyto(lv["z"][:h, :w], self._result, casting="same_kind")
        shapes = [(h, w)]
        k = 0
        # Down: each coarser cell averages the known cells of its 2 x 2 block, until no
        # hole is left or the grid is one cell wide.
        while min(shapes[-1]) > 1:
            h, w = shapes[-1]
            z, kn = self._levels[k]["z"], self._levels[k]["known"].view(np.uint8)
            shape = ((h + 1) // 2, (w + 1) // 2)
            nxt = self._level(k + 1, shape)
            shapes.append(shape)
            k += 1
            total = nxt["z"][: shape[0], : shape[1]]
            np.add(z[0::2, 0::2], z[0::2, 1::2], out=total)
            total += z[1::2, 0::2]
            total += z[1::2, 1::2]
            count = (kn[0::2, 0::2] + kn[0::2, 1::2]) + (kn[1::2, 0::2] + kn[1::2, 1::2])
            miss = nxt["miss"]
            np.equal(count, 0, out=miss)
            total /= np.maximum(count, 1)  # 0 where nothing is known
            np.logical_not(miss, out=nxt["known"][: shape[0], : shape[1]])
            if not miss.any():
                break
        top_lv = self._levels[k]
        top = top_lv["z"][: shapes[k][0], : shapes[k][1]]
        if top_lv["miss"].any():  # one cell wide and still holes: the mean of the known
            top[top_lv["miss"]] = top.sum() / np.count_nonzero(~top_lv["miss"])
        # Up: each level's holes take the coarser cell's value and are relaxed. Branch-free
        # (see _relax): known + missing x coarse, with `z` 0 in the holes.
        for j in range(k - 1, -1, -1):
            lv = self._levels[j]
            hj, wj = shapes[j]
            pad, avg, known = lv["pad"], lv["avg"], lv["z"][:hj, :wj]
            out = pad[1:-1, 1:-1]
            np.copyto(avg, lv["miss"])  # 1.0 in the holes
            for di in (0, 1):
                for dj in (0, 1):
                    part = out[di::2, dj::2]
                    np.multiply(avg[di::2, dj::2], top[: part.shape[0], : part.shape[1]],
                                out=part)
            out += known
            if smoothing and lv["miss"].any():
                quarter = lv["quarter"]
                np.multiply(avg, 0.25, out=quarter)
                _relax(pad, avg, quarter, known, smoothing)
            top = out
        # The known cells exact, the holes from the pyramid (known + missing x filled, as
        # above); contiguous, so that lookups index it without a copy.
        filled = self._levels[0]["avg"]
        np.multiply(top, self._levels[0]["miss"], out=filled)
        self._result += filled
        return self._result


def inpaint(grid: np.ndarray, smoothing: int = 4) -> np.ndarray:
    """Fill NaN (or infinite) cells of a (rows, cols) grid: averages down a 2 x 2 pyramid
    until no hole is left, then back up, each level's holes taken from the coarser level
    and relaxed by `smoothing` rounds of 4-neighbour averaging. O(cells); known cells are
    kept.
    Returns a new array (or `grid` itself when it has no hole or no known cell)."""
    out = _Inpainter(grid.shape)(grid, smoothing)
    return out if out is grid else out.copy()


def _window_extreme(grid: np.ndarray, radius: int, axis: int, ufunc: np.ufunc, fill: float,
                    out: np.ndarray, work: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """out = `ufunc` (np.minimum or np.maximum) of (rows, cols) `grid` over the 2 radius + 1
    cells centred on each cell along `axis`, the window cut at the grid's edges (`fill`
    the ufunc's identity: +inf or -inf). The same as scipy.ndimage's minimum / maximum
    filters in mode "reflect", 5-8 x faster (473 x 431 grid): runs of doubling length over
    contiguous memory (log2(window) passes) instead of a per-element queue. `out` may be
    `grid`.
    work: two flat float64 buffers of at least (rows + 2 radius) x (cols + 2 radius)."""
    h, w = grid.shape
    width = 2 * radius + 1
    shape, step = ((h + 2 * radius, w), w) if axis == 0 else ((h, w + 2 * radius), 1)
    size = shape[0] * shape[1]
    a, b = work[0][:size], work[1][:size]
    padded = a.reshape(shape)
    if axis == 0:
        padded[:radius], padded[h + radius:], padded[radius:h + radius] = fill, fill, grid
    else:
        padded[:, :radius], padded[:, w + radius:] = fill, fill
        padded[:, radius:w + radius] = grid
    # Flat passes: a run never crosses a row of the padded array where it is used.
    span, valid = 1, size
    while 2 * span <= width:
        k = span * step
        ufunc(a[: valid - k], a[k:valid], out=b[: valid - k])
        a, b = b, a
        valid -= k
        span *= 2
    runs = a.reshape(shape)  # runs[p] = extreme of padded[p : p + span] along axis
    lag = width - span
    if axis == 0:
        return ufunc(runs[:h], runs[lag:lag + h], out=out)
    return ufunc(runs[:, :w], runs[:, lag:lag + w], out=out)


def _neighbour_min(grid: np.ndarray, half: int) -> np.ndarray:
    """(rows, cols) minimum of the (2 half + 1)^2 cells around each cell, the cell itself
    left out, of a (rows, cols) grid (inf outside it). Rows above and below the cell
    take the row minima, the cell's own row the cells to its left and right."""
    h, w = grid.shape
    padded = np.full((h + 2 * half, w + 2 * half), np.inf)
    padded[half:half + h, half:half + w] = grid
    rows = padded[:, : w].copy()  # minimum over the whole window width, per padded row
    for k in range(1, 2 * half + 1):
        np.minimum(rows, padded[:, k:k + w], out=rows)
    out = rows[:h].copy()
    for k in range(1, 2 * half + 1):
        if k != half:
            np.minimum(out, rows[k:k + h], out=out)
    for k in range(2 * half + 1):
        if k != half:
            np.minimum(out, padded[half:half + h, k:k + w], out=out)
    return out


class _Opening:
    """Progressive morphological opening of (rows, cols) grids of one shape, work arrays kept.

    Square windows, not SMRF's disks. A square fits a diagonal strip only up to 0.35 of its
    width (a disk up to 0.5), so it cuts diagonal embankments that a disk leaves; but disks
    flag low objects later (when slope x radius is higher), scored worse on ISPRS as a
    whole, and are 10 x slower with scipy's footprints (docs/measurements.md, "Ground
    filter: how the hybrid got here").

    The opening itself runs in float32 (its passes are memory-bound, as the in-painting's:
    7-10 % faster). Steps equal to the threshold to the centimetre may round either way
    (7 labels of the real files' 1.84 M points changed with it). The values are centred
    micrometres, so a cloud moved by whole metres still rounds the same. `work`, `scratch`
    and `eroded` (float64) serve the rim, peak and island windows.
    """

    def __init__(self, shape: tuple[int, int], max_radius: int) -> None:
        size = (shape[0] + 2 * max_radius) * (shape[1] + 2 * max_radius)
        self.work = (np.empty(size), np.empty(size))
        self.eroded, self.scratch = np.empty(shape), np.empty(shape)
        f = np.float32
        self._work = (np.empty(size, f), np.empty(size, f))
        self._eroded, self._opened, self._last, self._scratch = (np.empty(shape, f)
                                                                 for _ in range(4))
        self._flags = np.empty(shape, bool)

    def __call__(self, first: np.ndarray, radii: list[int], steep_radius: int,
                 rise_per_cell: float) -> tuple[np.ndarray, np.ndarray]:
        """((rows, cols) bool object cells, the same after the radii up to `steep_radius`)
        of the opening of (rows, cols) `first` by growing square windows; a cell is an
        object when an opening step lowers it by more than rise_per_cell x radius.

        Squares absorb smaller squares, so the opening of the previous opening by radius r
        is the opening of the first surface by r: its erosion comes from the previous
        erosion by the few cells r grew (exact, min and max only)."""
        work, scratch, flags = self._work, self._scratch, self._flags
        eroded, opened, last = self._eroded, self._opened, self._last
        np.copyto(eroded, first)
        np.copyto(last, first)
        objects = np.zeros(first.shape, bool)
        near = objects
        previous = 0
        for radius in radii:
            grow = radius - previous
            _window_extreme(eroded, grow, 0, np.minimum, np.inf, scratch, work)
            _window_extreme(scratch, grow, 1, np.minimum, np.inf, eroded, work)
            _window_extreme(eroded, radius, 0, np.maximum, -np.inf, scratch, work)
            _window_extreme(scratch, radius, 1, np.maximum, -np.inf, opened, work)
            np.subtract(last, opened, out=scratch)
            objects |= np.greater(scratch, rise_per_cell * radius, out=flags)
            last, opened = opened, last
            previous = radius
            if radius == steep_radius:
                near = objects.copy()
        self._opened, self._last = opened, last
        return objects, near


def _median_trend(grid: np.ndarray, block: int, window: int) -> np.ndarray:
    """(rows, cols) large-scale trend of a (rows, cols) grid without holes: medians of
    block x block cells, a median filter of `window` blocks over them, and bilinear
    interpolation back to the cells (block centres)."""
    from scipy import ndimage

    h, w = grid.shape
    hb, wb = -(-h // block), -(-w // block)
    padded = np.pad(grid, ((0, hb * block - h), (0, wb * block - w)), mode="edge")
    coarse = np.median(padded.reshape(hb, block, wb, block).transpose(0, 2, 1, 3)
                       .reshape(hb, wb, block * block), axis=2)
    coarse = ndimage.median_filter(coarse, size=window, mode="nearest")
    rows = _linear_weights(w, block, wb)
    cols = _linear_weights(h, block, hb)
    across = coarse[:, rows[0]] * rows[2] + coarse[:, rows[1]] * rows[3]  # (hb, w)
    return across[cols[0]] * cols[2][:, None] + across[cols[1]] * cols[3][:, None]


def _linear_weights(n: int, block: int, nb: int) -> tuple[np.ndarray, ...]:
    """Linear interpolation of n cells from nb block centres (block cells each): the two
    block indices and their weights per cell, (n,) each; constant beyond the end centres."""
    pos = np.clip((np.arange(n) + 0.5) / block - 0.5, 0, nb - 1)
    lo = np.minimum(np.floor(pos).astype(np.int64), max(nb - 2, 0))
    hi = np.minimum(lo + 1, nb - 1)
    frac = pos - lo
    return lo, hi, 1.0 - frac, frac


class Bilinear:
    """Bilinear lookup of (rows = y, cols = x) grids of cell-centred values at fixed points:
    the four corner indices and weights are computed once and reused for every grid.

    shape: (rows, cols) of the grids; origin: (2,) x, y of the lower-left corner of cell
    (0, 0), metres; cell: cell edge, metres; xy: (M, 2) float64 points, metres (clamped
    to the cell centres' box)."""

    def __init__(self, shape: tuple[int, int], origin: np.ndarray, cell: float,
                 xy: np.ndarray) -> None:
        # One column at a time and in place: ~2 x faster than on (M, 2) arrays with
        # temporaries, which cost ~1 ms per 50 000-point message.
        h, w = shape
        x = (xy[:, 0] - origin[0]) / cell - 0.5
        y = (xy[:, 1] - origin[1]) / cell - 0.5
        np.clip(x, 0, w - 1, out=x)
        np.clip(y, 0, h - 1, out=y)
        x0, y0 = x.astype(np.int64), y.astype(np.int64)  # >= 0: truncation is floor
        np.minimum(x0, max(w - 2, 0), out=x0)
        np.minimum(y0, max(h - 2, 0), out=y0)
        x -= x0  # the fractions
        y -= y0
        idx = np.empty((4, len(x)), np.int64)  # corners (x0, y0), (x1, y0), (x0, y1), (x1, y1)
        np.multiply(y0, w, out=idx[0])
        idx[0] += x0
        right, up = int(w > 1), w if h > 1 else 0  # a strip one cell wide has one corner
        np.add(idx[0], right, out=idx[1])
        np.add(idx[0], up, out=idx[2])
        np.add(idx[2], right, out=idx[3])
        wts = np.empty((4, len(x)))
        np.subtract(1.0, x, out=wts[1])
        np.subtract(1.0, y, out=wts[2])
        np.multiply(wts[1], wts[2], out=wts[0])  # (1 - fx)(1 - fy)
        np.multiply(wts[1], y, out=wts[2])  # (1 - fx) fy
        np.multiply(x, 1.0 - y, out=wts[1])  # fx (1 - fy)
        np.multiply(x, y, out=wts[3])  # fx fy
        self.idx, self.wts = idx, wts
        self._corners = np.empty(self.wts.shape)

    def __call__(self, grid: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(M,) values of (rows, cols) `grid` at the points (into `out` if given)."""
        c = self._corners
        np.take(grid.ravel(), self.idx, out=c)
        c *= self.wts
        out = np.add(c[0], c[1], out=out)
        out += c[2]
        out += c[3]
        return out


def _grid_min(flat: np.ndarray, z: np.ndarray, shape: tuple[int, int],
              out: np.ndarray | None = None, empty: float = np.nan) -> np.ndarray:
    """(rows, cols) lowest z per cell of points in flat cells `flat`, `empty` (NaN or inf)
    where a cell has none; a point with an infinite z is none. Written into `out` if given."""
    out = np.empty(shape) if out is None else out
    flat_out = out.reshape(-1)
    flat_out.fill(np.inf)
    np.minimum.at(flat_out, flat, z)
    if not np.isinf(empty):
        flat_out[np.isinf(flat_out)] = empty
    return out


def _slope(surface: np.ndarray, cell: float) -> np.ndarray:
    """(rows, cols) gradient magnitude (rise over run) of a (rows, cols) grid of heights in
    metres on `cell` m cells; zero for a strip one cell wide (no slope to measure).
    Central differences inside, one-sided at the edges (np.gradient's, without its
    temporaries)."""
    if min(surface.shape) < 2:
        return np.zeros_like(surface)
    gy, gx = np.empty(surface.shape), np.empty(surface.shape)
    np.subtract(surface[2:], surface[:-2], out=gy[1:-1])
    gy[1:-1] /= 2.0 * cell
    np.subtract(surface[1], surface[0], out=gy[0])
    np.subtract(surface[-1], surface[-2], out=gy[-1])
    gy[[0, -1]] /= cell
    np.subtract(surface[:, 2:], surface[:, :-2], out=gx[:, 1:-1])
    gx[:, 1:-1] /= 2.0 * cell
    np.subtract(surface[:, 1], surface[:, 0], out=gx[:, 0])
    np.subtract(surface[:, -1], surface[:, -2], out=gx[:, -1])
    gx[:, [0, -1]] /= cell
    # sqrt(gx^2 + gy^2) rather than np.hypot: 10 x faster (hypot guards against overflow,
    # which metres cannot reach), the same to the last bit or two.
    np.multiply(gx, gx, out=gx)
    np.multiply(gy, gy, out=gy)
    gx += gy
    return np.sqrt(gx, out=gx)


def _ground_density(flat: np.ndarray, ground: np.ndarray, shape: tuple[int, int],
                    cell: float) -> np.ndarray:
    """(N,) ground points per m^2 over the 3 x 3 cells around each of the N points.

    flat: (N + F,) flat cell index of the points, then of the context points (all ground);
    ground: (N,) bool. Cells outside the grid count as empty."""
    n = len(ground)
    counts = np.bincount(np.concatenate([flat[:n][ground], flat[n:]]),
                         minlength=shape[0] * shape[1]).reshape(shape).astype(np.float64)
    padded = np.zeros((shape[0] + 2, shape[1] + 2))
    padded[1:-1, 1:-1] = counts
    rows = padded[:-2] + padded[1:-1] + padded[2:]
    box = rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:]
    return box.ravel()[flat[:n]] / (9.0 * cell * cell)


def _dense_band(band: np.ndarray, density: np.ndarray, cfg: HybridSettings) -> np.ndarray:
    """(N,) acceptance band (m) narrowed by `threshold - dense_threshold` in full where the
    (N,) ground density (points per m^2) reaches `dense_full`, linearly from `dense_from`.
    Returns `band` itself where no point is dense enough."""
    ramp = (density - cfg.dense_from) / max(cfg.dense_full - cfg.dense_from, 1e-9)
    if not (ramp > 0).any():
        return band
    return band - (cfg.threshold - cfg.dense_threshold) * np.clip(ramp, 0.0, 1.0)


def _steep_objects(objects: np.ndarray, near: np.ndarray, slope: np.ndarray,
                   steep_slope: float) -> np.ndarray:
    """(rows, cols) bool object cells: the small-window flags `near` where the ground
    surface's `slope` (rise over run) exceeds `steep_slope`, the full opening's `objects`
    elsewhere. Returns `objects` itself (the same array) when nothing changes.

    Why: the large windows take a whole narrow terrace, embankment top or spur on steep
    ground for a building (it is narrower than the window and more than slope x radius
    above what the window leaves), and steep ground rarely carries large buildings.
    """
    steep = slope > steep_slope
    if not steep.any():
        return objects
    mixed = np.where(steep, near, objects)
    return objects if np.array_equal(mixed, objects) else mixed


def _half_disc_sums(rel: np.ndarray, valid: np.ndarray, directions: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """((M, D, K) float32 1 where neighbour K lies in the half-disc ahead of point M in
    direction D, 0 elsewhere; (M, D, 10) float64 sums over each half-disc of 1, x, y, z, xx,
    xy, yy, xz, yz, zz) of the K neighbours (M, K, 3) float32 m `rel` of M points, relative
    to each point, where (M, K) bool `valid`; D = `directions` half-discs, evenly turned."""
    x, y, zz = rel[..., 0], rel[..., 1], rel[..., 2]
    ang = np.arange(directions) * (2 * np.pi / directions)
    proj = np.multiply.outer(np.cos(ang).astype(np.float32), x)
    proj += np.multiply.outer(np.sin(ang).astype(np.float32), y)
    w = ((proj > 0) & valid).astype(np.float32).transpose(1, 0, 2)
    feats = np.empty(x.shape + (10,), np.float32)
    feats[..., 0] = 1.0
    feats[..., 1], feats[..., 2], feats[..., 3] = x, y, zz
    np.multiply(x, x, out=feats[..., 4])
    np.multiply(x, y, out=feats[..., 5])
    np.multiply(y, y, out=feats[..., 6])
    np.multiply(x, zz, out=feats[..., 7])
    np.multiply(y, zz, out=feats[..., 8])
    np.multiply(zz, zz, out=feats[..., 9])
    return w, np.matmul(w, feats).astype(np.float64)


def _half_disc_planes(sums: np.ndarray) -> tuple[np.ndarray, ...]:
    """The least-squares planes z = a + bx x + by y of the half-discs whose (M, D, 10)
    `sums` `_half_disc_sums` gives, each (M, D): (bool ok: 4 points or more, not all on a
    line; a, the plane's height at the point, m; bx, by, its slopes; its residual
    variance, m^2; the smaller eigenvalue of the covariance of the points' x and y, m^2).
    Centred: a is found at the half-disc's centroid, then moved to the point (x = y = 0)."""
    n, sx, sy, sz, sxx, sxy, syy, sxz, syz, szz = np.moveaxis(sums, -1, 0)
    nz = np.maximum(n, 1.0)
    mx, my, mz = sx / nz, sy / nz, sz / nz
    cxx = sxx / nz - mx * mx
    cyy = syy / nz - my * my
    cxy = sxy / nz - mx * my
    cxz = sxz / nz - mx * mz
    cyz = syz / nz - my * mz
    czz = szz / nz - mz * mz
    det = cxx * cyy - cxy * cxy
    ok = (n >= 4) & (det > 1e-9)
    det = np.where(ok, det, 1.0)
    bx = (cxz * cyy - cyz * cxy) / det
    by = (cyz * cxx - cxz * cxy) / det
    a = mz - bx * mx - by * my
    rms2 = czz - bx * cxz - by * cyz  # residual variance of the fit
    lam = (cxx + cyy) / 2 - np.sqrt(((cxx - cyy) / 2) ** 2 + cxy ** 2)
    return ok, a, bx, by, rms2, lam


def _rim_points(xyz: np.ndarray, flat: np.ndarray, windows: "_GroundWindows",
                candidates: np.ndarray, ground_idx: np.ndarray,
                cfg: HybridSettings) -> np.ndarray:
    """(M,) indices, among `candidates`, of points on the rim of a plateau of ground points:
    within `rim_band` above (or `rim_below` below) the least-squares plane of the ground
    points in a half-disc on one side of them, that plane smooth (rms < `rim_max_rms`),
    not steep (< `rim_max_slope`), spread in two dimensions (smallest standard deviation
    > `rim_spread`, so not a contour line of a hillside) and reaching within `rim_near` of
    the point. Only points with ground at their own level within `rim_window` and ground
    more than `rim_drop` below them there (the cliff, on the raster of ground cells) are
    judged (a pre-selection that both scores better and leaves ~12 % of the candidates),
    against their `rim_neighbours` nearest ground points within `rim_window`, in
    `rim_directions` half-discs.

    xyz: (N + F, 3) m, points and context; flat: (N + F,) their flat cells; windows: the
    highest and lowest ground around each cell, and the points near given points;
    candidates: indices of the rejected points; ground_idx: indices of the ground points
    (context included).

    Why: the opening cuts the rims of terrace steps and cliffs (the step's foot is within
    the window), and the in-painted surface under a rim point mixes the plateau with the
    foot of the step, so the band leaves it out. A tree, a bush or a wall is above the
    plane of the ground beside it; a roof has no ground plateau at its level.
    """
    cand = windows.between(xyz[:, 2], flat, candidates, above=-cfg.rim_band,
                           below=max(cfg.rim_drop, cfg.rim_band))
    if len(cand) == 0:
        return cand
    gp, d, nn = windows.nearest_ground(xyz, cand, ground_idx, cfg.rim_neighbours,
                                       cfg.rim_window)
    k = d.shape[1]
    if k < 4:
        return cand[:0]
    C = xyz[cand]
    valid = np.isfinite(d)
    nn[~valid] = 0
    rel = gp[nn]
    rel -= C[:, None, :]
    rel = rel.astype(np.float32)  # metres from the point: float32 is exact enough, 2 x faster
    w, sums = _half_disc_sums(rel, valid, cfg.rim_directions)
    ok, a, bx, by, rms2, lam = _half_disc_planes(sums)
    # The nearest neighbour in the wedge (the queries come sorted by distance).
    first = np.argmax(w > 0, axis=2)
    dmin = np.take_along_axis(np.broadcast_to(d[:, None, :], w.shape), first[..., None], 2)[..., 0]
    acc = (ok & (rms2 < cfg.rim_max_rms ** 2) & (lam > cfg.rim_spread ** 2)
           & (bx * bx + by * by < cfg.rim_max_slope ** 2) & (dmin < cfg.rim_near)
           & (-a < cfg.rim_band) & (-a > -cfg.rim_below))
    return cand[acc.any(axis=1)]


class _GroundWindows:
    """The highest (`high`) and lowest (`low`) ground within `radius` cells of each cell,
    flat (rows x cols,), computed once for the rim and face passes, and the points near
    given points by blocks of radius + 1 cells (a point within `radius` cells of another
    is in its block or a neighbouring one): 3 x 3 blocks on a grid 1 / 49 the size replace
    the two window passes per test that marked the cells near the candidates."""

    def __init__(self, ground_grid: np.ndarray, flat: np.ndarray, radius: int,
                 opening: _Opening) -> None:
        work, scratch, out = opening.work, opening.scratch, opening.eroded
        high = np.where(np.isinf(ground_grid), -np.inf, ground_grid)
        _window_extreme(high, radius, 0, np.maximum, -np.inf, scratch, work)
        self.high = _window_extreme(scratch, radius, 1, np.maximum, -np.inf, out,
                                    work).ravel().copy()
        _window_extreme(ground_grid, radius, 0, np.minimum, np.inf, scratch, work)
        self.low = _window_extreme(scratch, radius, 1, np.minimum, np.inf, out, work).ravel().copy()
        self.shape = ground_grid.shape
        self.block = radius + 1
        cols = self.shape[1]
        rows_b = -(-self.shape[0] // self.block)
        cols_b = -(-cols // self.block)
        self.bshape = (rows_b, cols_b)
        row, col = np.divmod(flat, cols)
        self.bflat = (row // self.block) * cols_b + col // self.block

    def between(self, z: np.ndarray, flat: np.ndarray, candidates: np.ndarray, *,
                above: float, below: float) -> np.ndarray:
        """The candidate point indices with ground higher than their z (m) + `above` and
        lower than their z - `below` within the window of their flat cell."""
        cand = candidates[self.high[flat[candidates]] > z[candidates] + above]
        return cand[self.low[flat[cand]] < z[cand] - below]

    def nearest_ground(self, xyz: np.ndarray, cand: np.ndarray, ground_idx: np.ndarray,
                       k: int, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ground points (G, 3) near the candidates `cand` (indices into xyz), and per
        candidate the map distances (M, k') and indices into those (M, k') of its k' =
        min(k, G) nearest within `radius` m (inf and G where fewer)."""
        gp = xyz[self.near(cand, ground_idx)]
        k = min(k, len(gp))
        if k == 0:
            return gp, np.zeros((len(cand), 0)), np.zeros((len(cand), 0), np.int64)
        # An unbalanced, uncompacted tree: 2-3 x faster to build, the queries as fast.
        tree = cKDTree(gp[:, :2], balanced_tree=False, compact_nodes=False)
        d, nn = tree.query(xyz[cand, :2], k=k, distance_upper_bound=radius)
        return gp, d.reshape(len(cand), k), nn.reshape(len(cand), k)

    def near(self, points: np.ndarray, others: np.ndarray) -> np.ndarray:
        """The indices in `others` of points in the 3 x 3 blocks around the blocks of the
        point indices `points`."""
        mark = np.zeros((self.bshape[0] + 2, self.bshape[1] + 2), bool)
        inner = np.zeros(self.bshape[0] * self.bshape[1], bool)
        inner[self.bflat[points]] = True
        mark[1:-1, 1:-1] = inner.reshape(self.bshape)
        grown = mark[1:-1, 1:-1].copy()
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di or dj:
                    grown |= mark[1 + di:1 + di + self.bshape[0], 1 + dj:1 + dj + self.bshape[1]]
        return others[grown.ravel()[self.bflat[others]]]


def _face_points(xyz: np.ndarray, flat: np.ndarray, windows: "_GroundWindows",
                 candidates: np.ndarray, ground_idx: np.ndarray,
                 cfg: HybridSettings) -> np.ndarray:
    """(M,) indices, among `candidates`, of points on the face of a cliff or terrace wall:
    among their `face_neighbours` nearest ground points within `face_radius` there is one
    more than `face_rise` above and one more than `face_rise` below them that rise faster
    than `face_steep` (rise over run) from the lower to the upper. Only points with ground
    that high and that low in the raster windows (`windows`, of `rim_window`) are judged.

    xyz, flat: points and context and their flat cells; candidates: indices of rejected
    points; ground_idx: indices of the ground points (context included).

    Why: a quarry's cliff between two ground levels (ISPRS samp53) holds points all the
    way up its face; the opening cuts them with the rim, the rim test wants a plateau at
    their level, and the band cannot follow a surface that rises 10 m in a cell. A wall
    has a roof, not ground, above it; a tree on a hillside has ground above and below it,
    but the ground there rises at the hillside's slope, not at a cliff's.
    """
    cand = windows.between(xyz[:, 2], flat, candidates, above=cfg.face_rise,
                           below=cfg.face_rise)
    if len(cand) == 0:
        return cand
    gp, d, nn = windows.nearest_ground(xyz, cand, ground_idx, cfg.face_neighbours,
                                       cfg.face_radius)
    if d.shape[1] < 2:
        return cand[:0]
    valid = np.isfinite(d)
    nn[~valid] = 0
    rel = gp[nn]
    rel -= xyz[cand][:, None, :]
    rel = rel.astype(np.float32)
    up = valid & (rel[..., 2] > cfg.face_rise)
    down = valid & (rel[..., 2] < -cfg.face_rise)
    some = up.any(axis=1) & down.any(axis=1)
    cand, rel, up, down = cand[some], rel[some], up[some], down[some]
    dz = rel[:, :, None, 2] - rel[:, None, :, 2]
    dx = rel[:, :, None, 0] - rel[:, None, :, 0]
    dy = rel[:, :, None, 1] - rel[:, None, :, 1]
    # (M, upper K, lower K): rise over run above face_steep, compared squared (no root).
    steep = (dz > 0) & (dz * dz > cfg.face_steep ** 2 * (dx * dx + dy * dy))
    ok = (up[:, :, None] & down[:, None, :] & steep).any(axis=(1, 2))
    return cand[ok]


def _peak_points(top: np.ndarray, z_kept: np.ndarray, flat: np.ndarray, n: int,
                 radius: int, rise: float, opening: _Opening) -> np.ndarray:
    """(n,) bool: the ground points among the first n more than `rise` above the highest
    ground point of every other cell within `radius` cells (square), with at least one
    such cell. top: (rows, cols) highest ground point per cell, -inf where none; z_kept:
    (N + F,) heights of the ground points (the context included), +inf for the others;
    flat: their flat cells; `opening`: its work arrays are reused.

    Why: on sparse scans (ISPRS Vaihingen, 2-3.5 m spacing) a bush, a hedge's end or a
    low wall is often one point in its cell, the band of the rebuilt surface accepts it,
    and the surface is then rebuilt through it (Type II 13-15 % on samp51/52/53/71; those
    points lie a median 0.7-1.3 m above the reference ground beside them). Ground is rarely
    higher than everything within 5 m: a slope has higher ground uphill, a ridge along
    itself, a rim on its plateau.

    Only the cells that are the highest of their window are judged; the window is taken
    again with all of them removed. Two such cells within one window are equally high
    (the windows are symmetric), so neither rises above the other: a judged cell with
    another one in its window is no peak.
    """
    work, scratch, highest = opening.work, opening.scratch, opening.eroded
    _window_extreme(top, radius, 0, np.maximum, -np.inf, scratch, work)
    _window_extreme(scratch, radius, 1, np.maximum, -np.inf, highest, work)
    judged = np.isfinite(top) & (top >= highest)
    # Judged cells per window: box sums of a summed-area table.
    h, w = top.shape
    table = np.zeros((h + 1, w + 1), np.int32)
    np.cumsum(np.cumsum(judged, axis=0, dtype=np.int32), axis=1, out=table[1:, 1:])
    r0 = np.clip(np.arange(h) - radius, 0, h)
    r1 = np.clip(np.arange(h) + radius + 1, 0, h)
    c0 = np.clip(np.arange(w) - radius, 0, w)
    c1 = np.clip(np.arange(w) + radius + 1, 0, w)
    count = (table[r1][:, c1] - table[r0][:, c1]) - (table[r1][:, c0] - table[r0][:, c0])
    judged &= count == 1
    others = np.where(judged, -np.inf, top)
    _window_extreme(others, radius, 0, np.maximum, -np.inf, scratch, work)
    _window_extreme(scratch, radius, 1, np.maximum, -np.inf, highest, work)
    cells = flat[:n]
    # +inf (not ground) never passes: the bound is finite or -inf only where no ground.
    bound = highest.ravel()[cells]
    return (judged.ravel()[cells] & (z_kept[:n] > bound + rise) & (bound > -np.inf)
            & (z_kept[:n] < np.inf))


def _lone_low_cells(grid: np.ndarray, occupied: np.ndarray, reach: int, cfg: HybridSettings
                    ) -> np.ndarray:
    """(rows, cols) bool: the cells of (rows, cols) `grid` (lowest ground point per cell,
    +inf where none; `occupied` its finite cells) in pieces of at most `lone_cells` with
    no other ground within `reach` cells, whose lowest point lies more than `low_outlier`
    plus `lone_slope` times the distance below each of the (up to 8) nearest ground cells
    of other pieces within `lone_reach` m (3 or more of them). Pieces, not single cells:
    two or three echoes of one strip a few metres apart shielded each other. Judged on
    the first labels' ground: before them, the nearest cells of a street seen alone
    between roofs are all roofs.

    The low-blunder test's window is empty there. A low noise echo at a strip's far edge
    lies beyond the last scan line (the longer range along an oblique beam is further
    out as well as lower), alone: taken for ground, it sank the surface under the strip's
    edge and a bubble of the rolling DEM 20 m wide and 5-15 m deep around it."""
    from scipy import ndimage

    # Pieces of cells at most `reach` cells apart: squares of radius r round two cells
    # touch when the cells are at most 2 r + 1 apart
    grown = ndimage.maximum_filter(occupied, 2 * (reach // 2) + 1, mode="constant")
    pieces, _ = ndimage.label(grown, structure=np.ones((3, 3), bool))
    size = np.bincount(pieces[occupied])
    lone = occupied & (size[pieces] <= cfg.lone_cells)
    out = np.zeros(grid.shape, bool)
    if not lone.any():
        return out
    # only the ground within lone_reach of a lone cell (a tree of all of it cost ~9 ms on
    # an ISPRS sample of 33 000 cells with 16 lone ones)
    span = int(np.ceil(cfg.lone_reach / cfg.cell))
    others = occupied & ~lone & ndimage.maximum_filter(lone, 2 * span + 1, mode="constant")
    if others.sum() < 3:
        return out
    c = cfg.cell
    lr, lc = np.nonzero(lone)
    orr, occ = np.nonzero(others)
    dist, near = cKDTree(np.column_stack([orr, occ]) * c).query(
        np.column_stack([lr, lc]) * c, k=8, distance_upper_bound=cfg.lone_reach)
    found = np.isfinite(dist)
    z_near = np.where(found, grid[orr[near.clip(0, len(orr) - 1)],
                                  occ[near.clip(0, len(occ) - 1)]], np.inf)
    floor = np.min(z_near - cfg.lone_slope * np.where(found, dist, 0.0), axis=1)
    low = (found.sum(axis=1) >= 3) & (grid[lr, lc] < floor - cfg.low_outlier)
    out[lr[low], lc[low]] = True
    return out


def _ground_pieces(grid: np.ndarray, index: np.ndarray, connect: float) -> tuple[int, np.ndarray]:
    """(the number of pieces, (C,) the piece of each of the C occupied cells) of (rows, cols)
    `grid`, the lowest ground point per cell (m, +inf where none): cells joined through
    their 8 neighbours where their heights differ by at most `connect` m. index: (rows,
    cols) the number of each occupied cell, row by row, -1 where empty."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows, cols = grid.shape
    n = int(np.count_nonzero(index >= 0))
    links = []
    with np.errstate(invalid="ignore"):  # inf - inf between empty cells: no link
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            c0, c1 = max(0, -dc), cols - max(0, dc)
            a, b = grid[: rows - dr, c0:c1], grid[dr:, c0 + dc:c1 + dc]
            joined = np.abs(a - b) <= connect
            links.append((index[: rows - dr, c0:c1][joined],
                          index[dr:, c0 + dc:c1 + dc][joined]))
    first = np.concatenate([a for a, _ in links])
    second = np.concatenate([b for _, b in links])
    graph = coo_matrix((np.ones(len(first), np.int8), (first, second)), shape=(n, n))
    count, piece = connected_components(graph, directed=False)
    return count, piece


def _higher_ground_around(grid: np.ndarray, index: np.ndarray, piece: np.ndarray,
                          sunk: np.ndarray, own: np.ndarray, reach: int, cfg: HybridSettings
                          ) -> tuple[np.ndarray, np.ndarray]:
    """For K cells `sunk` (flat indices into (rows, cols) `grid`, the lowest ground point
    per cell, m, +inf where none) of pieces `own` (K,): ((K,) bool ground of another piece
    more than `island_rise` higher within `reach` cells, (K,) bool a pit: such higher
    ground, of any piece, in `island_pit_share` or more of the other cells of the window
    inside the grid). index: (rows, cols) occupied cells' numbers, -1 where empty; piece:
    (C,) the piece of each occupied cell."""
    rows, cols = grid.shape
    r, q = np.divmod(sunk, cols)
    dr, dq = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    rr, qq = r[:, None] + dr.ravel(), q[:, None] + dq.ravel()
    inside = (rr >= 0) & (rr < rows) & (qq >= 0) & (qq < cols)
    rr, qq = rr.clip(0, rows - 1), qq.clip(0, cols - 1)
    window = np.where(inside, grid[rr, qq], np.inf)
    with np.errstate(invalid="ignore"):
        higher = (window > grid.ravel()[sunk, None] + cfg.island_rise) & np.isfinite(window)
    # Higher ground of another piece: a pitched roof rising 2 m within the reach has
    # its own ridge above its eaves (simulated urban flight, seed 2: 2 565 points of a
    # roof 10-13 m up taken for ground in one message)
    other = (higher & (piece[index[rr, qq]] != own[:, None])).any(axis=1)
    pit = higher.sum(axis=1) >= cfg.island_pit_share * (inside.sum(axis=1) - 1)
    return other, pit


def _piece_extents(island: np.ndarray, piece: np.ndarray, occupied: np.ndarray,
                   cell: float) -> np.ndarray:
    """(P,) m, the extent (rows or columns, the wider) of each of the P pieces flagged in
    (P,) bool `island`; meaningless for the others. piece: (C,) the piece of each of the
    (rows, cols) bool `occupied` cells, row by row. Only the flagged pieces' cells are
    read (few)."""
    rows, cols = occupied.shape
    count = len(island)
    cells = np.flatnonzero(island[piece])
    row, col = np.divmod(np.flatnonzero(occupied.ravel())[cells], cols)
    lo_r, hi_r = np.full(count, rows), np.full(count, -1)
    lo_c, hi_c = np.full(count, cols), np.full(count, -1)
    which = piece[cells]
    np.minimum.at(lo_r, which, row)
    np.maximum.at(hi_r, which, row)
    np.minimum.at(lo_c, which, col)
    np.maximum.at(hi_c, which, col)
    return (np.maximum(hi_r - lo_r, hi_c - lo_c) + 1) * cell


def _islands_and_pits(grid: np.ndarray, cfg: HybridSettings, opening: _Opening
                      ) -> tuple[np.ndarray, np.ndarray]:
    """((rows, cols) bool cells of raised islands of ground, the same of pits) in
    (rows, cols) `grid`, the lowest ground point per cell (+inf where none).

    A piece is a set of ground cells joined through neighbours (8 of them) whose heights
    differ by at most `island_connect`: a wall or a cliff splits pieces, a slope does not.
    An island is a piece at most `island_extent` across, some of whose cells have ground
    more than `island_rise` below them within `island_reach`, and none ground of another
    piece more than that above them (a steep roof's ridge stands over its own eaves). A
    roof's ground is such a piece; a terrace has the hill above it, a hilltop slopes down,
    and a quarry's rim is wider than a roof. Lower ground counts in
    pieces of `island_min_cells` or more, and not in a pit: a cell whose window (within
    `island_reach`, inside the grid) is `island_pit_share` or more higher ground. Stray low
    points the blunder test missed are such pits; a street beside a roof has the street,
    the building's shadow or the strip's edge around it too. Pits of pieces of at most
    `pit_cells` cells are returned.
    `opening`: its work arrays are reused (the opening is done).
    """
    c = cfg.cell
    occupied = np.isfinite(grid)
    n = int(occupied.sum())
    out, pits = np.zeros(grid.shape, bool), np.zeros(grid.shape, bool)
    if n < 2:
        return out, pits
    index = np.full(grid.shape, -1, np.int64)
    index[occupied] = np.arange(n)
    count, piece = _ground_pieces(grid, index, cfg.island_connect)
    reach = max(1, int(round(cfg.island_reach / c)))
    work, scratch, around = opening.work, opening.scratch, opening.eroded
    # Higher ground within reach of each cell: what raises nothing is judged on it.
    _window_extreme(np.where(occupied, grid, -np.inf), reach, 0, np.maximum, -np.inf,
                    scratch, work)
    _window_extreme(scratch, reach, 1, np.maximum, -np.inf, around, work)
    has_higher = around > grid + cfg.island_rise
    above = np.zeros(count, bool)
    # Lower ground that counts: pieces of island_min_cells or more, pits left out.
    size = np.bincount(piece, minlength=count)
    lower = np.full(grid.shape, np.inf)
    lower[occupied] = np.where(size[piece] >= cfg.island_min_cells, grid[occupied], np.inf)
    sunk = np.flatnonzero(has_higher)
    if len(sunk):
        own = piece[index.ravel()[sunk]]
        other_higher, pit = _higher_ground_around(grid, index, piece, sunk, own, reach, cfg)
        above[own[other_higher]] = True
        lower.ravel()[sunk[pit]] = np.inf
        pits.ravel()[sunk[pit & (size[own] <= cfg.pit_cells)]] = True
    _window_extreme(lower, reach, 0, np.minimum, np.inf, scratch, work)
    _window_extreme(scratch, reach, 1, np.minimum, np.inf, around, work)
    below = np.bincount(piece, (around < grid - cfg.island_rise)[occupied], count) > 0
    island = below & ~above
    if not island.any():
        return out, pits
    island &= _piece_extents(island, piece, occupied, c) <= cfg.island_extent
    out[occupied] = island[piece]
    return out, pits


@dataclass
class _Raster:
    """The grid a cloud is filtered on (rows = y, cols = x, `cell` m cells) and the cell of
    each of its points. The first `n` points are the cloud's, the rest context ground."""

    cell: float  # m
    n: int  # the cloud's points (N); the other F of `xyz` are context
    xyz: np.ndarray  # (N + F, 3) m, the points, then the context
    z: np.ndarray  # (N + F,) m, xyz's heights, contiguous
    origin: np.ndarray  # (2,) m, x and y of the lower-left corner of cell (0, 0)
    shape: tuple[int, int]  # (rows, cols)
    flat: np.ndarray  # (N + F,) int64 flat cell of each point: row x cols + col

    @classmethod
    def of(cls, pts: np.ndarray, fixed: np.ndarray | None, cfg: HybridSettings) -> _Raster:
        """The grid of `cfg.cell` m cells over (N, 3) centred points `pts` and (F, 3) context
        ground `fixed` (m), its corner `cfg.anchor` cells before their lowest x and y.
        CloudFormatError when they span too many cells (`check_extent`)."""
        c = cfg.cell
        allp = pts if fixed is None else np.concatenate([pts, fixed])
        check_extent(allp, c)
        origin = (np.array([allp[:, 0].min(), allp[:, 1].min()])  # (axis-0 reductions are slow)
                  - c * np.asarray(cfg.anchor, dtype=np.float64))
        # (a point on a cell's edge: see cell_index)
        col, row = (cell_index(allp[:, a] - origin[a], c) for a in (0, 1))
        shape = (int(row.max()) + 1, int(col.max()) + 1)  # rows = y, cols = x
        return cls(cell=c, n=len(pts), xyz=allp, z=np.ascontiguousarray(allp[:, 2]),
                   origin=origin, shape=shape, flat=row * shape[1] + col)


@dataclass
class _Labels:
    """The hybrid filter's labels after the label rounds, and the ground they make; the
    steps after the rounds update them in place."""

    ground: np.ndarray  # (N,) bool
    usable: np.ndarray  # (N,) bool: neither a low blunder nor a lone echo, so may be ground
    # (N + F,) m: z of the ground points and of the context (but its low blunders), +inf
    # for the others: they enter the surface's lowest points as no point
    z_kept: np.ndarray
    band: np.ndarray  # (N,) m, how far from the surface a ground point may lie
    surface: np.ndarray  # (rows, cols) m, the in-painted surface the labels were judged on
    grid: np.ndarray  # (rows, cols) m, lowest ground point per cell, +inf where none
    have_grid: bool  # whether a round built `grid` (if not, it is uninitialised)
    sparse: bool  # the median ground density of the first labels is under `dense_from`

    def leave_ground(self, leave: np.ndarray, raster: _Raster) -> None:
        """The points of (N,) bool `leave` are no longer ground; `grid` follows."""
        self.ground = self.ground & ~leave
        self.z_kept[:raster.n][leave] = np.inf
        _grid_min(raster.flat, self.z_kept, raster.shape, out=self.grid, empty=np.inf)


def _low_blunders(raster: _Raster, cfg: HybridSettings) -> tuple[np.ndarray, np.ndarray]:
    """((N + F,) bool low blunders, (rows, cols) m lowest point per cell of the other points,
    NaN where none).

    A low blunder lies more than `low_outlier` below the lowest point of the other cells of
    the `low_window` x `low_window` square around its own. (A median would also flag
    narrow ground between roofs, such as rail tracks.) Again without those found, up to
    LOW_ROUNDS times: echoes come in twos and threes a few metres apart, and a deeper one
    shielded a shallower one, which stayed ground."""
    flat, z, shape = raster.flat, raster.z, raster.shape
    zmin = _grid_min(flat, z, shape)
    low = np.zeros(len(z), bool)
    for _ in range(LOW_ROUNDS):
        neighbour_min = _neighbour_min(np.where(np.isnan(zmin), np.inf, zmin),
                                       cfg.low_window // 2)
        nb = neighbour_min.ravel()[flat]
        new = np.isfinite(nb) & (z < nb - cfg.low_outlier) & ~low
        if not new.any():
            break
        low |= new
        zmin = _grid_min(flat[~low], z[~low], shape)
    return low, zmin


def _opening_radii(cfg: HybridSettings) -> tuple[list[int], int]:
    """(the opening's window radii in cells, ascending, the last `window`; the radius up to
    which the flags count on steep ground, `steep_window`, in cells).

    Radii grow one cell at a time up to `fine_window`, then two: the large windows only
    remove whole buildings, which a 2-cell step finds as well (18 % faster, ISPRS total
    error 0.04 points better)."""
    c = cfg.cell
    max_radius = max(1, int(round(cfg.window / c)))
    steep_radius = min(max(1, int(round(cfg.steep_window / c))), max_radius)
    fine_radius = max(1, int(round(cfg.fine_window / c)))
    radii = [r for r in range(1, max_radius + 1)
             if r <= fine_radius or (r - fine_radius) % 2 == 0 or r == max_radius]
    return radii, steep_radius


def _without(zmin: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(rows, cols) m: the lowest points per cell `zmin` (NaN where none), NaN on the
    (rows, cols) bool object cells too: what the ground surface is in-painted from."""
    return np.where(objects | np.isnan(zmin), np.nan, zmin)


def _object_cells(zmin: np.ndarray, first: np.ndarray, opening: _Opening, fill: _Inpainter,
                  radii: list[int], steep_radius: int, cfg: HybridSettings
                  ) -> tuple[np.ndarray, np.ndarray]:
    """((rows, cols) bool object cells, the same from the radii up to `steep_radius` only)
    of the progressive opening of `first`, the in-painted (rows, cols) lowest points `zmin`
    (m, NaN where none), by the square windows of `radii` cells.

    With `trend_window`, the object cells are those of a second opening, of `first` minus
    the median trend of the ground surface after the first opening (see HybridSettings),
    and the steep-window flags those of both."""
    c = cfg.cell
    objects, near = opening(first, radii, steep_radius, cfg.slope * c)
    if cfg.trend_window > 0:
        ground0 = fill(_without(zmin, objects))
        # An odd number of blocks: the median of a plane is then the plane (centred).
        window = 2 * max(0, int(round((cfg.trend_window / (c * cfg.trend_block) - 1) / 2))) + 1
        trend = _median_trend(ground0, cfg.trend_block, window)
        objects, detrended_near = opening(first - trend, radii, steep_radius, cfg.slope * c)
        near = near & detrended_near
    return objects, near


def _object_free_surface(zmin: np.ndarray, objects: np.ndarray, near: np.ndarray,
                         fill: _Inpainter, cfg: HybridSettings) -> tuple[np.ndarray, np.ndarray]:
    """((rows, cols) m ground surface in-painted across the object cells, (rows, cols) its
    slope, rise over run) from the lowest points per cell `zmin` (m, NaN where none).

    The object cells are `objects`, but where that surface is steeper than `steep_slope`
    the small-window flags `near` (see _steep_objects), and the surface is then in-painted
    again. The surface may be `fill`'s own array, which its next call overwrites."""
    surface = fill(_without(zmin, objects))
    slope_grid = _slope(surface, cfg.cell)
    mixed = _steep_objects(objects, near, slope_grid, cfg.steep_slope)
    if mixed is not objects:
        surface = fill(_without(zmin, mixed))
        slope_grid = _slope(surface, cfg.cell)
    return surface, slope_grid


def _lone_echoes(raster: _Raster, grid: np.ndarray, z_kept: np.ndarray, cfg: HybridSettings
                 ) -> np.ndarray:
    """(N + F,) bool: the ground points within `low_outlier` of the floor of a lone low
    cell (see _lone_low_cells) of (rows, cols) `grid`, the lowest ground point per cell (m,
    +inf where none); z_kept: (N + F,) m heights of the ground points, +inf for the others."""
    flat = raster.flat
    lone = _lone_low_cells(grid, np.isfinite(grid), cfg.low_window // 2, cfg).ravel()[flat]
    lone &= z_kept < grid.ravel()[flat] + cfg.low_outlier
    return lone


def _label_rounds(raster: _Raster, at: Bilinear, fill: _Inpainter, surface: np.ndarray,
                  slope_grid: np.ndarray, low: np.ndarray, cfg: HybridSettings) -> _Labels:
    """The labels of the points judged against the ground surface, rebuilt from them, up to
    `passes` rounds or until the labels repeat.

    surface, slope_grid: (rows, cols) m and rise over run, the object-free surface and its
    slope; at: the bilinear lookup at the cloud's N points; low: (N + F,) bool low
    blunders, never ground. A point is ground within the band of the surface: `threshold`
    plus `scalar` x the slope (capped at 1), narrowed on dense ground after the first
    round (see _dense_band). After the first round the lone echoes (see _lone_low_cells)
    leave the ground for good. Each round rebuilds the surface from the points now taken
    as ground (and the context), so that ground the opening cut off (terrace rims, ridges)
    rejoins once its neighbours have raised the surface under it."""
    n, z, flat, shape = raster.n, raster.z, raster.flat, raster.shape
    # Slope capped at 1 (45 degrees): at the foot of a wall or a tower leg the raster
    # gradient is huge, and an uncapped band would take the structure for ground.
    band = cfg.threshold + cfg.scalar * np.minimum(at(slope_grid), 1.0)
    ground = np.zeros(n, bool)
    usable = ~low[:n]
    # The context is always ground, but for its low blunders.
    z_kept = np.where(low, np.inf, z)
    gap = np.empty(n)
    grid = np.empty(shape)
    have_grid = False
    sparse = False
    for i in range(cfg.passes):
        np.subtract(z[:n], at(surface, out=gap), out=gap)
        in_band = np.less_equal(np.abs(gap, out=gap), band) & usable
        if i and np.array_equal(in_band, ground):
            break  # converged: the surface would be rebuilt from the same points
        ground = in_band
        if i == 0:
            density = _ground_density(flat, ground, shape, raster.cell)
            band = _dense_band(band, density, cfg)
            # Sparse scans (face and peak tests; no island test): the median ground density
            # of the first labels under `dense_from`.
            sparse = bool(ground.any()) and float(np.median(density[ground])) < cfg.dense_from
        if ground.any() or len(z) > n:
            np.copyto(z_kept[:n], z[:n])
            np.copyto(z_kept[:n], np.inf, where=~ground)
            _grid_min(flat, z_kept, shape, out=grid, empty=np.inf)
            if i == 0 and cfg.lone_reach > 0:
                lone = _lone_echoes(raster, grid, z_kept, cfg)
                if lone.any():
                    usable &= ~lone[:n]
                    ground = ground & ~lone[:n]
                    z_kept[lone] = np.inf
                    _grid_min(flat, z_kept, shape, out=grid, empty=np.inf)
            surface = fill(grid)
            have_grid = True
    return _Labels(ground=ground, usable=usable, z_kept=z_kept, band=band, surface=surface,
                   grid=grid, have_grid=have_grid, sparse=sparse)


def _drop_islands_and_pits(raster: _Raster, labels: _Labels, at: Bilinear, fill: _Inpainter,
                           opening: _Opening, cfg: HybridSettings) -> bool:
    """The ground points of raised islands, of pits (within `island_rise` of the pit's
    floor) and of the walls under the islands' edges leave the ground (see
    _islands_and_pits); `labels` updated in place. Returns whether any point left."""
    n, z, cells = raster.n, raster.z, raster.flat[:raster.n]
    islands, pits = _islands_and_pits(labels.grid, cfg, opening)
    leave = islands.ravel()[cells] | (pits.ravel()[cells]
                                      & (z[:n] < labels.grid.ravel()[cells] + cfg.island_rise))
    leave &= labels.ground
    if not leave.any():
        return False
    labels.leave_ground(leave, raster)
    # The walls under an island's edges were in the band of the surface across the roof;
    # on the surface without it they stand metres up and leave too (simulated urban
    # flights: wall points 1-3 m up labelled ground).
    surface = fill(labels.grid)
    gap = np.subtract(z[:n], at(surface))
    wall = labels.ground & (np.abs(gap, out=gap) > labels.band)
    if wall.any():
        labels.leave_ground(wall, raster)
    return True


def _add_rims_and_faces(raster: _Raster, labels: _Labels, zmin: np.ndarray, opening: _Opening,
                        cfg: HybridSettings) -> list[np.ndarray]:
    """Rejected points on the rims of plateaus (see _rim_points) and, on sparse scans, on
    cliff faces (see _face_points) join the ground, in `rim_passes` passes; `labels` updated
    in place (`ground` a new array; `grid` lowered where they join, the surface not
    rebuilt). zmin: (rows, cols) m lowest point per cell, blunders left out (NaN where
    none). Returns the indices into the N points of those that joined, one array per test
    that gave any."""
    n, z, flat = raster.n, raster.z, raster.flat
    usable, z_kept = labels.usable, labels.z_kept
    # Only the lowest point of its cell is judged for rims (the same answers, 30 % fewer
    # candidates); cliff faces are judged on all points (steep faces hold several).
    judge = ~labels.ground & usable & (z[:n] <= zmin.ravel()[flat[:n]])
    ground = labels.ground = labels.ground.copy()
    grid_flat = labels.grid.reshape(-1)
    # The highest and lowest ground around each cell are taken once, before the first
    # pass: they only pre-select the candidates; each test reads the ground points.
    windows = _GroundWindows(labels.grid, flat, max(1, int(round(cfg.rim_window / raster.cell))),
                             opening)
    added: list[np.ndarray] = []
    # Not on dense scans: there the opening resolves what faces it can, and on the AHN
    # corridor the test took bushes on ditch banks.
    faces = cfg.face_radius > 0 and labels.sparse

    def join(new: np.ndarray) -> None:
        if len(new):
            ground[new] = True
            z_kept[new] = z[new]
            np.minimum.at(grid_flat, flat[new], z[new])
            added.append(new)

    for rim_pass in range(max(1, cfg.rim_passes)):
        cand = np.flatnonzero(judge & ~ground)
        if rim_pass:  # only near what the passes before gave back
            cand = windows.near(np.concatenate(added), cand) if added else cand[:0]
        join(_rim_points(raster.xyz, flat, windows, cand, np.flatnonzero(np.isfinite(z_kept)),
                         cfg))
        if faces and rim_pass < cfg.rim_passes - 1:  # on the ground with these rims
            join(_face_points(raster.xyz, flat, windows, np.flatnonzero(usable & ~ground),
                              np.flatnonzero(np.isfinite(z_kept)), cfg))
    return added


def _drop_peaks(raster: _Raster, labels: _Labels, opening: _Opening, cfg: HybridSettings
                ) -> bool:
    """Single raised ground points (see _peak_points) leave the ground, `peak_passes` times;
    `labels` updated in place (`ground` too: the array is changed, not replaced). Returns
    whether any point left."""
    n, flat = raster.n, raster.flat
    z_kept, grid_flat = labels.z_kept, labels.grid.reshape(-1)
    radius = max(1, int(round(cfg.peak_window / raster.cell)))
    kept = np.isfinite(z_kept)
    top = np.full(grid_flat.size, -np.inf)  # highest ground point per cell
    np.maximum.at(top, flat[kept], z_kept[kept])
    peaks = False
    for _ in range(cfg.peak_passes):
        peak = _peak_points(top.reshape(raster.shape), z_kept, flat, n, radius, cfg.peak_rise,
                            opening)
        if not peak.any():
            break
        labels.ground &= ~peak
        z_kept[:n][peak] = np.inf
        peaks = True
        # The highest and lowest ground of the cells that lost a point, again.
        hit = np.zeros(grid_flat.size, bool)
        hit[flat[:n][peak]] = True
        top[hit], grid_flat[hit] = -np.inf, np.inf
        again = np.flatnonzero(hit[flat] & np.isfinite(z_kept))
        np.maximum.at(top, flat[again], z_kept[again])
        np.minimum.at(grid_flat, flat[again], z_kept[again])
    return peaks


def _sparse_cell(pts: np.ndarray, fixed: np.ndarray | None, cfg: HybridSettings
                 ) -> HybridSettings:
    """`cfg`, with a coarser cell when points (N, 3) and context (F, 3) m are far sparser
    than its grid (`sparse_grid_cell`): 50 points spread over 5 x 5 km made 25 million
    cells of 1 m to in-paint, 13 s and 3.6 GB for one cloud."""
    import dataclasses

    parts = [p[:, :2] for p in (pts, fixed) if p is not None and len(p)]
    lo = np.min([column_min(p) for p in parts], axis=0)
    hi = np.max([column_max(p) for p in parts], axis=0)
    cell = sparse_grid_cell(cfg.cell, lo, hi, sum(len(p) for p in parts))
    return cfg if cell == cfg.cell else dataclasses.replace(cfg, cell=cell)


def morphological_ground(pts: np.ndarray, cfg: HybridSettings, *,
                         fixed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Raster ground filter (progressive morphological opening, as SMRF, made robust).

    pts: (N, 3) centred points, m; fixed: (F, 3) context ground points (grid data only).
    Returns ((N,) bool ground, (N,) ground height under each point, m). Everything is
    raster work on the small grid of lowest points plus one bilinear lookup per point;
    the grid-sized work arrays are allocated once per call and reused (see _Inpainter).

    The steps: low blunders out (`_low_blunders`); the object cells of the opening
    (`_object_cells`) and the surface without them (`_object_free_surface`); the label
    rounds against the rebuilt surface (`_label_rounds`); then, on dense scans, raised
    islands and pits out (`_drop_islands_and_pits`); rims and cliff faces in
    (`_add_rims_and_faces`) and, on sparse scans, single raised points out
    (`_drop_peaks`); the surface rebuilt when they changed the ground. A cloud far
    sparser than its grid of `cfg.cell` is filtered on coarser cells (`_sparse_cell`).
    """
    cfg = _sparse_cell(pts, fixed, cfg)
    c = cfg.cell
    raster = _Raster.of(pts, fixed, cfg)
    low, zmin = _low_blunders(raster, cfg)
    fill = _Inpainter(raster.shape)
    radii, steep_radius = _opening_radii(cfg)
    first = fill(zmin).copy()
    # (its work arrays also serve the rim, peak and island windows, which may be the wider)
    opening = _Opening(raster.shape, max(radii[-1], int(round(cfg.rim_window / c)),
                                         int(round(cfg.peak_window / c)),
                                         int(round(cfg.island_reach / c))))
    objects, near = _object_cells(zmin, first, opening, fill, radii, steep_radius, cfg)
    surface, slope_grid = _object_free_surface(zmin, objects, near, fill, cfg)
    at = Bilinear(raster.shape, raster.origin, c, pts[:, :2])
    labels = _label_rounds(raster, at, fill, surface, slope_grid, low, cfg)
    rebuild = False  # the ground changed since the labels' surface was in-painted
    if cfg.island_rise > 0 and labels.have_grid and not labels.sparse:
        rebuild = _drop_islands_and_pits(raster, labels, at, fill, opening, cfg)
    if cfg.rim_window > 0 and labels.have_grid:
        added = _add_rims_and_faces(raster, labels, zmin, opening, cfg)
        # (the peak test runs only with the rim test on)
        peaks = labels.sparse and cfg.peak_window > 0 and _drop_peaks(raster, labels,
                                                                      opening, cfg)
        if added or peaks:
            # The surface through them too: their height above ground is then ~0 (the
            # surface in-painted across the step put them metres up, and the DEM, which
            # takes only the ground near the surface, lost the rims).
            rebuild = True
    surface = fill(labels.grid) if rebuild else labels.surface
    return labels.ground, at(surface)


class GroundSurface:
    """Piecewise-linear ground from ground points (G, 3) float64 metres (the TIN of their
    XY); nearest ground point outside the hull."""

    def __init__(self, ground_xyz: np.ndarray) -> None:
        self.xyz = ground_xyz
        self.tri: Delaunay | None = None
        if len(ground_xyz) >= 3:
            try:
                self.tri = Delaunay(ground_xyz[:, :2])
            except QhullError:
                self.tri = None
        self.tree = cKDTree(ground_xyz[:, :2]) if len(ground_xyz) else None

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(M,) ground height in metres at xy (M, 2) metres; NaN when there is no ground at
        all."""
        out = np.full(len(xy), np.nan)
        if self.tree is None:
            return out
        todo = np.ones(len(xy), bool)
        if self.tri is not None:
            s = self.tri.find_simplex(xy)
            inside = s >= 0
            if inside.any():
                t = self.tri.transform[s[inside]]
                b = np.einsum("ijk,ik->ij", t[:, :2], xy[inside] - t[:, 2])
                bary = np.column_stack([b, 1 - b.sum(axis=1)])
                out[inside] = np.einsum("ij,ij->i", bary,
                                        self.xyz[self.tri.simplices[s[inside]], 2])
                todo = ~inside
        if todo.any():
            _, nn = tree_query(self.tree, xy[todo], workers=-1)
            out[todo] = self.xyz[nn, 2]
        return out


def _ransac_tiles(xyz: np.ndarray, tiling: TilingConfig, rcfg: RansacConfig,
                  rng: np.random.Generator, fixed: np.ndarray | None
                  ) -> tuple[np.ndarray, int, int]:
    """Per-tile RANSAC ground with automatic re-tiling of poor tiles."""
    ground = np.zeros(len(xyz), bool)
    lo = column_min(xyz[:, :2])
    hi = column_max(xyz[:, :2])
    # cores are [corner, corner + size): one more tile where the extent is a whole number
    # of tiles, or the points on the far edges fell in none and were never ground
    nx, ny = ((hi - lo) // tiling.size).astype(int) + 1
    queue = [(lo + np.array([i, j]) * tiling.size, tiling.size, 0)
             for i in range(nx) for j in range(ny)]
    tiles = splits = 0
    fixed = np.zeros((0, 3)) if fixed is None else fixed
    # A tile's points come from the x-sorted order (a binary search, then y), not a pass
    # over every point per tile: O(N x tiles) was seconds on a 774 000-point survey.
    by_x = np.argsort(xyz[:, 0], kind="stable")
    xs = xyz[by_x, 0]

    def in_box(box_lo: np.ndarray, box_hi: np.ndarray) -> np.ndarray:
        """Indices (ascending, as a mask would give them) of the points in the box."""
        i0, i1 = np.searchsorted(xs, [box_lo[0], box_hi[0]])
        cand = by_x[i0:i1]
        y = xyz[cand, 1]
        return np.sort(cand[(y >= box_lo[1]) & (y < box_hi[1])])

    while queue:
        corner, size, depth = queue.pop()
        ov = tiling.overlap
        inner = in_box(corner - ov, corner + size + ov)
        inner_xy = xyz[inner, :2]
        core = all_columns((inner_xy >= corner) & (inner_xy < corner + size))
        if not core.any():
            continue
        f_in = all_columns((fixed[:, :2] >= corner - ov) & (fixed[:, :2] < corner + size + ov))
        pts = np.concatenate([xyz[inner], fixed[f_in]])
        tiles += 1
        res = ransac_plane(pts, distance_threshold=rcfg.distance_threshold,
                           probability=rcfg.probability, max_trials=rcfg.max_trials, rng=rng,
                           max_tilt_deg=45.0)
        own = res.inliers[: len(inner)]
        if res.plane is not None and len(pts) >= 10:
            # The ground's shape from the lowest point of each cell (an eighth of the
            # tile): the inliers lie within the threshold by definition (their spread
            # could never pass max_residual), and all the points' span is the trees' and
            # towers' too (a 20 m pole split a flat tile five times).
            low = pts[lowest_per_cell(pts, corner - ov, size / 8.0)]
            resid = res.plane.distance(low)
            spread = 1.4826 * np.median(np.abs(resid - np.median(resid)))
            relief = np.ptp(low[:, 2])  # the paper's failures: blocks spanning relief
            poor = (res.inliers.mean() < tiling.min_inlier_ratio or spread > tiling.max_residual
                    or relief > tiling.max_relief)
            if poor and depth < tiling.max_depth and size / 2 >= tiling.min_size:
                splits += 1
                half = size / 2
                queue += [(corner + np.array([a, b]) * half, half, depth + 1)
                          for a in (0, 1) for b in (0, 1)]
                continue
        ground[inner[core & own]] = True
    return ground, tiles, splits


# The raster filter's grid at most (float64 work grids: ~10 x 8 bytes per cell).
MAX_RASTER_CELLS = 25_000_000
# The most a cloud may span in z, m: the earth's relief is ~20 km. More is bad coordinates,
# and overflows the obstacles' int64 voxel keys from ~7e5 m (50 km of XY, 0.06 m voxels).
MAX_RELIEF = 100_000.0
# The farthest a point may lie from the frame's origin, m (the earth's radius is 6.4e6 m):
# the context's cell keys hold +-1e9 cells of `context.cell` >= 0.1 m.
MAX_COORDINATE = 1e8

# Stray points: beyond the interquartile box of a cloud by this many IQRs plus this many
# metres (a uniform strip spans 2 IQRs; a UAV scan's far edge lies well inside).
FAR_IQRS = 3.0
FAR_MARGIN = 500.0  # m
# In z, beyond the height quartiles by FAR_IQRS IQRs plus this plus the diagonal of the
# cloud's footprint: terrain rising 1:1 across the whole cloud with the tallest building
# (828 m) on top stays inside. The real data's farthest point from its quartiles lies 61 m
# beyond 3 IQRs (ISPRS samp31; AHN corridor 42 m).
FAR_MARGIN_Z = 1000.0  # m


FAR_SAMPLE = 5000  # points whose quartiles bound the rest (about; all of a smaller cloud)
# Odd 64-bit constants (the golden ratio's and xxHash's) whose products mix every bit of a
# coordinate into the top bits, so that the sample is spread over a cloud's points.
_MIX_X, _MIX_Y = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xC2B2AE3D27D4EB4F)


def far_points(xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: points of xyz (N, 2 or 3) m far outside the rest of their cloud, a
    multipath return or a bad coordinate kilometres away: in XY beyond the quartile box by
    FAR_IQRS IQRs + FAR_MARGIN, in z (a third column) by FAR_IQRS IQRs + FAR_MARGIN_Z + the
    footprint's diagonal. Judged on the quartiles of about FAR_SAMPLE of the points, so a
    few strays cannot move the bounds, chosen by their coordinates, so the same points
    are far in whatever order the cloud comes (:func:`_order_free_sample`)."""
    n = len(xyz)
    if n < 8:
        return np.zeros(n, bool)
    pick = _order_free_sample(xyz, FAR_SAMPLE)
    sample = xyz if pick is None else np.take(xyz, pick, axis=0)  # (4 x xyz[pick]'s speed)
    # One column at a time: percentiles of an (M, 2) sample along axis 0 and the (N, 2)
    # comparisons cost ~0.8 ms per 50 000-point message, this ~0.2 ms (the same figures:
    # the same partition and interpolation per column).
    inside = np.ones(n, bool)
    for a in range(min(xyz.shape[1], 2)):
        col = xyz[:, a]
        q1, q3 = np.percentile(sample[:, a], [25.0, 75.0])
        reach = FAR_IQRS * (q3 - q1) + FAR_MARGIN
        inside &= col >= q1 - reach
        inside &= col <= q3 + reach
    if xyz.shape[1] > 2:
        sample = sample[inside if pick is None else inside[pick]]  # holds the quartiles
        footprint = np.hypot(np.ptp(sample[:, 0]), np.ptp(sample[:, 1]))
        z = xyz[:, 2]
        q1, q3 = np.percentile(sample[:, 2], [25.0, 75.0])
        reach = FAR_IQRS * (q3 - q1) + FAR_MARGIN_Z + footprint
        inside &= z >= q1 - reach
        inside &= z <= q3 + reach
    return ~inside


def _order_free_sample(xyz: np.ndarray, size: int) -> np.ndarray | None:
    """(M,) indices of about `size` of the points xyz (N, >= 2), chosen by their x and y
    alone (a hash of their bits below a threshold), never by their place in the array: a
    point is in the sample of any order of the same points, or of none. None: all of them
    (N <= 2 `size`, coordinates that are not float32/64, or points sharing so few x, y
    values that the sample came out too small: the quartiles of all, exact).

    Every k-th point would give a cloud in another order other quartiles, and the points
    near a bound would change sides. The quartiles of all points (np.partition) cost
    1.3 ms a column per 50 000 points, 15 ms per 500 000; this sample ~0.15 and ~2 ms."""
    n = len(xyz)
    if n <= 2 * size or xyz.dtype not in (np.float32, np.float64):
        return None
    bits = np.uint64 if xyz.dtype == np.float64 else np.uint32
    key = np.multiply(xyz[:, 1].view(bits), _MIX_Y)  # (wraps round: a hash, not a number)
    key ^= xyz[:, 0].view(bits)
    key *= _MIX_X
    pick = np.flatnonzero(key < np.uint64(min((size << 64) // n, 2 ** 64 - 1)))
    return pick if len(pick) >= size // 4 else None


def check_extent(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """CloudFormatError when points xyz (N >= 1, 3) m span more than MAX_RASTER_CELLS
    cells of `cell` m in XY or more than MAX_RELIEF in z, or lie beyond MAX_COORDINATE.
    Every ground method and the obstacles grid the cloud (the context's footprint and
    cell keys, voxels), so this is judged in floats before any cell index is cast to
    int64, which a span of 1e19 cells overflows. Returns the cloud's box: (3,) lowest and
    (3,) highest coordinates, m."""
    lo, hi = column_min(xyz), column_max(xyz)
    with np.errstate(over="ignore"):  # (1e300 m clouds: inf cells, refused just the same)
        cols, rows = np.floor((hi[:2] - lo[:2]) / cell) + 1
        cells = rows * cols
    if cells > MAX_RASTER_CELLS:
        raise CloudFormatError(
            f"the cloud spans {cols * cell:.6g} x {rows * cell:.6g} m, more than "
            f"{MAX_RASTER_CELLS:,} cells of ground.cell = {cell} m: cut it into tiles "
            "(las2bag --tile-size)")
    if hi[2] - lo[2] > MAX_RELIEF:
        raise CloudFormatError(f"the cloud spans {hi[2] - lo[2]:.3g} m in z, more than "
                               f"{MAX_RELIEF:.0f} m: its coordinates are not a scene")
    if max(-lo.min(), hi.max()) > MAX_COORDINATE:
        raise CloudFormatError(f"the cloud lies {max(-lo.min(), hi.max()):.3g} m from the "
                               f"frame's origin, more than {MAX_COORDINATE:.0e} m: its "
                               "coordinates are not a scene")
    return lo, hi


def _collinear_xy(pts: np.ndarray) -> bool:
    """Whether all points (N, 3) m lie on one line (or one spot) in XY: the smaller
    eigenvalue of their XY covariance is below 1e-12 of the larger. All the points, not a
    sample: every k-th point of an organized scan can be one column of it."""
    x, y = pts[:, 0] - pts[0, 0], pts[:, 1] - pts[0, 1]  # near 0: the sums below keep digits
    n = len(pts)
    mx, my = x.sum() / n, y.sum() / n
    sxx, syy, sxy = x @ x - n * mx * mx, y @ y - n * my * my, x @ y - n * mx * my
    half = 0.5 * (sxx + syy)
    large = half + np.sqrt(max(half * half - (sxx * syy - sxy * sxy), 0.0))
    # det / large: the small eigenvalue without the cancellation of half - sqrt(...)
    return bool(large <= 0 or (sxx * syy - sxy * sxy) / large <= 1e-12 * large)


def classify_ground(xyz: np.ndarray, *, tiling: TilingConfig, ground: GroundConfig,
                    tin: TinConfig, ransac: RansacConfig, context_xyz: np.ndarray | None = None,
                    rng: np.random.Generator | None = None) -> GroundResult:
    """Ground mask and height above ground of (N, 3) float64 points (metres, z up).

    context_xyz: (M, 3) ground of earlier messages (the streaming context) or None.
    Fewer than 3 points are all ground with height 0 (there is no surface to be above).
    Points collinear or coincident in XY go to the raster filter (`hybrid`) whatever
    `ground.method` says: a TIN or a plane needs an area. CloudFormatError when xyz is
    not (N, 3), holds a NaN or an infinity, or spans more than :func:`check_extent` allows.
    """
    t0 = time.perf_counter()
    xyz = points_xyz(xyz, "classify_ground")
    n = len(xyz)
    if n < 3:
        if n:
            check_extent(xyz, ground.cell)
        return GroundResult(np.ones(n, bool), np.zeros(n, np.float32), 0, 0, {"total": 0.0})
    lo, hi = check_extent(xyz, ground.cell)
    rng = rng or np.random.default_rng(ransac.seed)
    # Centred on the middle of the cloud's box, in whole metres: Qhull and float math stay
    # exact with UTM coordinates. Not on the mean of a sample taken by index (every k-th
    # point): that moved with the order of the points, and with it the float32 rounding of
    # the in-painted surface, so a shuffled cloud came out different (ISPRS samp23: one
    # point's ground label; ~4e-6 m of height above ground).
    # The centred coordinates are rounded to the micrometre: survey points lie on a 1 cm
    # lattice, so many sit exactly at a threshold of the filter (2 m below their
    # neighbours, 0.15 m above the ground around them), and the binary rounding of their
    # coordinates decided the side, differently once the cloud was moved by whole metres
    # (the 15 ISPRS samples moved 2 km up: 85 ground labels changed, 46 of them samp12's;
    # corridor 07CZ2_14: 20). Rounded, the filter sees the same numbers wherever whole
    # metres put the cloud.
    origin = cell_index((lo + hi) / 2.0, 1.0).astype(np.float64)
    pts = snap_micrometres(xyz - origin)
    fixed = (None if context_xyz is None or len(context_xyz) == 0
             else snap_micrometres(context_xyz - origin))
    tiles, splits = 1, 0
    method = ground.method
    if _collinear_xy(pts):
        method = "hybrid"  # no TIN, no tiles; the raster copes
    if method == "hybrid":
        is_ground, z_ground = morphological_ground(pts, HybridSettings(cell=ground.cell,
                                                   slope=ground.slope, window=ground.window,
                                                   threshold=ground.threshold), fixed=fixed)
        t1 = time.perf_counter()
    else:
        # In the order of their coordinates, the context's too: RANSAC draws its samples by
        # index, Qhull's triangulation of cocircular points (a survey's lattice has many)
        # and the ties of the lowest point per cell and of one point per facet follow the
        # input's order, so a shuffled cloud changed 14-745 labels of an ISPRS sample with
        # `tin` and 550-2 700 with `ransac`. The sort is ~1 % of either method's time.
        order = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))
        pts = pts[order]
        if fixed is not None:
            fixed = fixed[np.lexsort((fixed[:, 2], fixed[:, 1], fixed[:, 0]))]
        if method == "ransac":
            is_ground, tiles, splits = _ransac_tiles(pts, tiling, ransac, rng, fixed)
        else:
            is_ground = tin_densification(pts, tin, fixed=fixed, drop_odd_seeds=True)
        t1 = time.perf_counter()
        g_pts = pts[is_ground] if fixed is None else np.concatenate([fixed, pts[is_ground]])
        z_ground = GroundSurface(g_pts).height(pts[:, :2])
        back = np.empty_like(order)
        back[order] = np.arange(n)
        is_ground, z_ground, pts = is_ground[back], z_ground[back], pts[back]
    hag = (pts[:, 2] - z_ground).astype(np.float32)
    t2 = time.perf_counter()
    return GroundResult(is_ground, hag, tiles, splits,
                        {"filter": t1 - t0, "surface": t2 - t1, "total": t2 - t0})
