"""Obstacle grouping and classification (ASPRS codes), and the clearance grid.

Per point, from the covariance of its neighbours within `feature_radius` (eigenvalues
l1 >= l2 >= l3): linearity (l1 - l2) / l1, planarity (l2 - l3) / l1, roughness sqrt(l3)
and the main axis (`local_shape`; inside a crown's solid mass none of them is sought).

1. Noise (7): points with too few neighbours within `noise_radius`, or far below ground.
2. Wires (14): linear, near-horizontal points high above ground with empty space below
   them, kept only when they join into long runs (a wire spans tens of metres). The
   pipeline remembers the wires of earlier messages: a short piece that continues one is
   wire too (at a wire's height a narrow scan strip catches it in pieces of a few metres).
3. The other points above `min_height` are grouped into objects: connected components of a
   voxel grid of edge `cluster_distance` (26-neighbourhood). Towers (15) are the tall
   objects that carry wires: wires touch their column, none passes above, and away from
   them the wires sag lower on every side (at a tree under the line they do not); the
   wires of another line crossing over at an angle (a lower line's tower beside a higher
   line's ground track) do not count against them. A tower once recognised is
   remembered by the pipeline, so later strips that catch only its legs still know it.
4. Buildings (6): smooth planar points joined into patches; a patch of at least
   `building_min_area` (in its own plane, so walls count) whose main plane, found by the
   paper's RANSAC with the robust eigenvalue fit, holds most of it is a roof or wall; one
   no plane holds is a curved roof or wall (a vault, a dome) when one quadric surface
   holds it and it is a solid, smooth sheet that stands steep where it meets the ground
   (not a crown's lacy smooth bits, not a heap of earth); rough points clinging to it
   (edges, chimneys) join it. A small patch continuing a roof or wall of an earlier
   message counts with it, and rough points clinging to one join it.
5. Wires are followed along their own axis through crowns and clutter, where they stop
   looking linear. Poles and other slender things are unclassified (1); the rest is
   vegetation by height above ground (3 < 0.5 m <= 4 <= 2 m < 5).

Measured on the AHN corridor and AHN4 tiles (benchmarks/bench_ground.py): k = 10 nearest
neighbours made scan lines on roofs look like wires; a 2 m radius does not. A thin strip
(a survey streamed in 0.1 s slices) borrows the candidates of the strips before it as
neighbours (`shape_context`): its edges cut most of its neighbourhoods.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lidar_obstacles.config import ClearanceConfig, ObstaclesConfig
from lidar_obstacles.core.arrays import (all_columns, cell_index, column_max, column_mean,
                                         column_min, eigenvector3, row_norm, symmetric_eig3,
                                         symmetric_eigenvalues3, tree_query, unique_ints)
from lidar_obstacles.core.classes import (
    BUILDING,
    GROUND,
    NOISE,
    TOWER,
    UNCLASSIFIED,
    WIRE,
    vegetation_class,
)
from lidar_obstacles.core.ransac import RANSAC_SEED, ransac_plane

PARALLEL_MIN = 20000  # query points x neighbours from which cKDTree runs on all cores
MAX_NEIGHBOURS = 32  # of the shape neighbourhoods: more add little but cost time
SOLID_NEIGHBOURS = 22  # of a coarse voxel's 26 neighbours occupied: inside a solid (local_shape)
# A tower's object holds its members up to this far (m) apart: a member hidden in a crown
# leaves a gap (07CZ2_14, 12AN2_20: 2-point pieces 8-9 m up, 2-3 m from the rest); towers
# stand 100 m and more apart.
TOWER_LINK = 5.0
OBJECT_LINK = 2.0  # m: voxel edge joining a building's or a wire's points into objects
DENSE_GRID_CELLS = 8_000_000  # voxel box up to which voxel work runs on a dense grid
BELOW_GROUND_NOISE = 1.5  # m: points this far below the ground surface are noise
WIRE_GAP = 2.5  # m: a wire point has no other point from this far below it up to 0.5 m
WIRE_MIN_RUN = 10.0  # m: wire candidates joined into shorter runs are not wires
# A thin earth wire is hit only every few metres: an isolated echo (no other point within
# `noise_radius`), or a piece too small to be an object, more than `wire_min_clearance` up
# that lies on the line of a wire found within WIRE_ECHO_REACH m, within WIRE_ECHO_TUBE +
# WIRE_ECHO_SAG x the distance along it, is that wire, not noise or vegetation (the two
# corridor tiles: all 20 isolated points more than 3 m up were such echoes, 3-8.6 m from
# the found wire).
WIRE_ECHO_REACH = 10.0
WIRE_ECHO_TUBE = 0.5  # m
WIRE_ECHO_SAG = 0.05  # m per m along the line
# A new wire (a run that continues no known wire) seen in fewer than SEED_VOXELS voxels of
# WIRE_MEMORY_VOXEL must run one way: the axes of its points agree in azimuth (the mean
# resultant of their doubled angles, 1 for parallel lines, ~0 for random ones) to at least
# SEED_AGREEMENT (see _seeds_run_one_way).
SEED_VOXELS = 20
# A known wire leads on (is followed, and continues this message's runs) only where the
# memory holds SEED_VOXELS voxels of wire that passed the wire test itself (not followed
# through a crown) within this reach (m): otherwise a few crown points taken for a wire
# once were followed through the crowns message after message, and what was followed was
# remembered and followed in turn.
KNOWN_WIRE_SUPPORT = 40.0
SEED_AGREEMENT = 0.95
WIRE_MEMORY_VOXEL = 0.5  # m: the wires a message passes on are thinned to one point per voxel
BUILDING_MEMORY_VOXEL = 1.0  # m: ... and its roofs and walls (the patches' own voxel)
WIRE_LINK = 4.0  # m: voxel edge joining wire candidates into runs (earth wires: 2-3 m gaps)
WIRE_STEP = 1.5  # m: how far a wire is followed from a known wire point per round
WIRE_TUBE = 0.15  # m: off a wire's line a followed point may lie (measured: 0.25 took leaves)
WIRE_DRIFT = 0.5  # m: off the line of the known wire a followed chain may end (sag)
WIRE_FOLLOW_ROUNDS = 12  # rounds of following: ~18 m of crown or clutter
KNOWN_WIRE_REACH = 3.0  # m: the first step from a wire of earlier messages (strips' gaps)
KNOWN_WIRE_AXIS_REACH = 5.0  # m: ... along the line of the known wire this close to it
TOWER_WIRE_GAP = 3.0  # m: a tower has wire points this close to it
TOWER_MIN_SPAN = 10.0  # m: ... and at least this much wire with a direction within SAG_FAR
LATTICE_VOXEL = 0.75  # m: voxels in which a tower's upper column is never solid (_lattice)
TOWER_MAX_SOLID = 0.05  # ... at most this share of its points in solid voxels
TOWER_PEAK = 5.0  # m: wire this little above a tower's top hangs from its peak
TOWER_ARM = 7.5  # m: ... or from its arms, this far from the axis (a low flight sees no peak)
SAG_NEAR, SAG_FAR = 15.0, 40.0  # m: ring around a tower where its wires must hang lower
SAG_MIN_DROP = 0.3  # m: how much lower (95th percentile of the wire there)
SAG_ONE_SIDE_RISE = 2.5  # m: how much higher, at most, when wire is seen on one side only
LINE_REACH = 2.0  # m: the wire (voxels) this close to a wire point give its direction on the map
LINE_SPREAD = 0.5  # m: ... when they spread at least this far along it (standard deviation)
LINE_ANGLE = 15.0  # deg: wires within this of each other's direction run as one line
LINE_SHARE = 0.2  # ... of the wire round an object at its height: a line it stands among
LINE_SAMPLE = 256  # about this many wire points round an object tell its lines
TOWER_BODY = (0.2, 0.35)  # towers: the band of the height (under the arms) whose spread
TOWER_TAPER = 0.2  # m per m below it, + TOWER_LEG_MARGIN m, bounds the legs' spread
TOWER_LEG_MARGIN = 1.0  # m
TOWER_FOOT_REACH = 1.0  # m: ground points this close to a tower's lowest points are its legs
TOWER_LEG_NEIGHBOURHOOD = 1.5  # m: ball (the objects' link) in which a leg point's neighbours
TOWER_LEG_CROWDING = 2.0  # ... number at most this many times the band's (90th percentile)
TOWER_RADIUS = 0.25  # towers: points within this share of the height from the top's axis
TOWER_BAND_MIN = 10  # points in the band TOWER_BODY from which its spread bounds the legs
PLANAR_SHARE = 0.4  # buildings: share of a planar patch on its main RANSAC plane
# ... or on planes found one after another, each holding PIECE_SHARE of it, up to
# MAX_PIECES of them (see _plane_pieces)
PIECES_SHARE, PIECE_SHARE, MAX_PIECES = 0.7, 0.05, 8
WALL_TILT = 20.0  # degrees: ... one of which is a wall, its normal this close to horizontal
CURVED_SHARE = 0.8  # ... or of a curved one on one quadric surface and that plane,
CURVED_SOLID = 0.5  # ... this share of whose cells (1 m, in its own plane) is inside it,
CURVED_ROUGH = 0.03  # ... with at most this share of rough points among its own,
CURVED_FOOT = 2.0  # m: ... and which is steep where it comes this close to the ground
CURVED_FOOT_NZ = np.cos(np.radians(45.0))  # (its normal's median z there at most this)
BUILDING_PLANARITY = 0.5  # (l2 - l3) / l1 of a roof or wall neighbourhood
BUILDING_REACH = 1.5  # m: rough points this close to a roof (edges, chimneys) join it
ROOF_WIRE_REACH = 1.0  # m: no wire this close to a known roof's 1 m voxel centroid
# The foot of a wall, below `obstacles.min_height` (not an obstacle candidate), is building
# where it lies within WALL_FOOT_REACH on the map of the building's points up to
# WALL_FOOT_BAND above that height (see _wall_feet).
WALL_FOOT_REACH = 0.25  # m
WALL_FOOT_BAND = 3.0  # m
# Structures, not buildings, wires or towers (cranes, masts): unclassified, not vegetation
# (see _structures)
STRUCTURE_MIN_HEIGHT = 5.0  # m
STRUCTURE_MIN_EXTENT = 7.0  # m, the box's horizontal diagonal
STRUCTURE_MIN_POINTS = 100  # fewer tell no share of beams
STRUCTURE_BEAMS = 0.1  # share of the object's points on steep lines
STRUCTURE_LINEARITY = 0.7
STRUCTURE_STEEP = 20.0  # degrees from horizontal, at least
STRUCTURE_ROUGHNESS = 0.25  # m, mean
# Poles, unclassified: objects whose box's horizontal diagonal is under POLE_MAX_EXTENT
# and whose top stands more than POLE_MIN_HEIGHT above ground
POLE_MAX_EXTENT = 2.0  # m
POLE_MIN_HEIGHT = 3.0  # m
QUADRIC_SAMPLE = 4096  # points at most on which a curved patch's quadric is fitted
THIN_SHARE = 1 / 3  # of a footprint within feature_radius of its edge: a thin strip (shape_context)


@dataclass(frozen=True)
class ObstacleObject:
    """One obstacle: ASPRS class, point count, box (m), height and clearance above ground."""

    id: int
    cls: int
    n_points: int
    min_xyz: np.ndarray
    max_xyz: np.ndarray
    height_above_ground: float  # highest point above ground, m
    clearance: float  # lowest point above ground (a wire's sag clearance), m


@dataclass(frozen=True)
class ObstacleClasses:
    """classes: (N,) uint8 ASPRS; object_id: (N,) int32 (-1 outside objects); towers:
    (T, 4) x, y, radius and height above ground (m) of the towers recognised, for the next
    message's known_towers;
    wires: (W, 4) x, y, z (m) and 1 where the wire passed the wire test itself, 0 where it
    was only followed (through a crown), the wire points thinned to one per
    WIRE_MEMORY_VOXEL, for its known_wires; buildings: (B, 4) x, y, z (m) and 1 for a
    roof or wall, 0 for what only clings to one (edges, chimneys), the building points
    thinned to one per BUILDING_MEMORY_VOXEL, for its known_buildings; candidates: (C, 3)
    m, the points whose shape was sought, for a later thin strip's shape_context."""

    classes: np.ndarray
    object_id: np.ndarray
    objects: tuple[ObstacleObject, ...]
    towers: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    wires: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    buildings: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @staticmethod
    def expand(part: "ObstacleClasses", where: np.ndarray, fill: int) -> "ObstacleClasses":
        """The classes of a cloud of N points whose points `where` ((N,) bool) are `part`;
        the others get class `fill` and no object."""
        classes = np.full(len(where), fill, np.uint8)
        object_id = np.full(len(where), -1, np.int32)
        classes[where], object_id[where] = part.classes, part.object_id
        return ObstacleClasses(classes, object_id, part.objects, part.towers, part.wires,
                               part.buildings, part.candidates)

    @staticmethod
    def repeat(part: "ObstacleClasses", inverse: np.ndarray) -> "ObstacleClasses":
        """The classes of a cloud of N points whose point i is point inverse[i] ((N,) int)
        of `part`'s (each copy of a point gets its class and object)."""
        return ObstacleClasses(part.classes[inverse], part.object_id[inverse], part.objects,
                               part.towers, part.wires, part.buildings, part.candidates)


def search_tree(points: np.ndarray) -> cKDTree:
    """A k-d tree of (M, D) points for exact neighbour queries, built the fast way: split at
    the middle of the box, not the median, and without shrinking the boxes (on a forest
    strip's 44 000 points 4.3 ms instead of 9.3 ms, queries no slower; the answers of an
    exact query do not depend on how the tree was split)."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def neighbour_pairs(query: np.ndarray, data: np.ndarray, radius: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i, j) of (Q, D) query and (P, D) data points no more than `radius` m
    apart, as two int64 arrays sorted by i, then j: what cKDTree.query_ball_point lists,
    without a Python list per query point. Those lists cost ~200 ms on a forest strip
    whose wire is followed through ~30 000 crown points for 12 rounds; this takes ~10 ms.
    Only the query points within the data's box (grown by the radius) are searched."""
    none = np.zeros(0, np.int64)
    if len(query) == 0 or len(data) == 0:
        return none, none
    lo, hi = column_min(data) - radius, column_max(data) + radius
    near = np.flatnonzero(all_columns((query >= lo) & (query <= hi)))
    if len(near) == 0:
        return none, none
    pairs = search_tree(query[near]).sparse_distance_matrix(
        search_tree(data), radius, output_type="ndarray")
    i, j = near[pairs["i"]], pairs["j"].astype(np.int64)
    order = np.lexsort((j, i))
    return i[order], j[order]


def _workers(n_queries: int, k: int = 1) -> int:
    """Threads for a cKDTree query of k neighbours each: all cores only when the query is
    large enough to pay for starting them (~1 ms per call on a 2-core machine, more than
    a small query costs). The shape features' search (k = 32) is worth it from ~600
    queries: on a forest strip's 12 000 queries, 51-69 ms on one core, 32 ms on two."""
    return -1 if n_queries * k >= PARALLEL_MIN else 1


@dataclass(frozen=True)
class LocalShape:
    """Per point, the shape of its neighbourhood (points within a radius): linearity
    (l1-l2)/l1 and planarity (l2-l3)/l1 (M,); main axis (M, 3) unit vectors; roughness
    sqrt(l3) (M,) metres, the spread off the best local plane."""

    linearity: np.ndarray
    planarity: np.ndarray
    axis: np.ndarray
    roughness: np.ndarray


def local_shape(xyz: np.ndarray, radius: float, max_neighbours: int = MAX_NEIGHBOURS,
                context: np.ndarray | None = None) -> LocalShape:
    """Shape features of (M, 3) points (m) from the covariance of their neighbourhood: the
    centroids of the fine voxels (edge radius / 8) within `radius` m (at most
    `max_neighbours`, the nearest) of the centroid of the point's coarse voxel (3 x 3 x 3
    fine voxels, 0.75 m at the default radius). Points of one coarse voxel share its
    shape; the neighbour search is most of the detector's time (0.5 m coarse voxels cost
    1.4 x as much for the same figures; 1 m ones lost roofs).

    A radius, not k nearest points: with k = 10 a roof scanned in lines 0.5 m apart looks
    linear (its ten nearest points lie on one scan line) and was taken for wires; within
    2 m a roof spans several lines and is planar, while a wire, even a bundle of
    sub-conductors 0.5 m apart, stays linear. Voxel centroids, not points: a densely
    scanned wire would fill max_neighbours within a few decimetres of the point, too short
    a piece to tell a line from a bundle; and a dense cloud costs no more than a sparse.

    A coarse voxel with SOLID_NEIGHBOURS or more of its 26 neighbours occupied lies inside
    a solid (a crown): a plane or a line through 3 x 3 x 3 voxels crosses at most ~21 of
    them. It is not searched and gets the shape of a filled block (linearity and planarity
    0, roughness the spread of a uniform 3-voxel block). None of the neighbourhoods that
    pass the wire test (linear, near-horizontal) or the roof test (planar, smooth) is
    solid on the AHN tiles or the simulated flights; a forest strip's coarse voxels are
    36 % solid, and its search 40 % shorter.

    context: (C, 3) m, points of earlier messages (`shape_context`): neighbours only, their
    own shape is not sought. The voxels stay aligned to xyz's, so where the context does
    not reach, the shapes are those without it."""
    m = len(xyz)
    lo = column_min(xyz) if m else np.zeros(3)
    coarse_edge = 3.0 * radius / 8.0
    if m >= 3 and context is not None and len(context):
        below = np.max(lo - column_min(context))  # whole coarse voxels, so both grids align
        lo = lo - max(np.ceil(below / coarse_edge), 0.0) * coarse_edge
        xyz_all = np.concatenate([xyz, context])
    else:
        xyz_all = xyz
    centre = _voxel_grid(xyz_all, lo, radius / 8.0)[0] if m >= 3 else xyz
    if len(centre) < 3:
        return LocalShape(np.zeros(m), np.zeros(m), np.tile([0.0, 0.0, 1.0], (m, 1)),
                          np.zeros(m))
    at, coarse, ijk = _voxel_grid(xyz_all, lo, coarse_edge)
    q = len(at)  # coarse voxels (query points)
    # per coarse voxel: a solid block's shape, replaced below where searched
    linearity, planarity = np.zeros(q), np.zeros(q)
    axis = np.tile([0.0, 0.0, 1.0], (q, 1))
    roughness = np.full(q, 3.0 * coarse_edge / np.sqrt(12.0))
    asked = _occupied_neighbours(ijk) < SOLID_NEIGHBOURS
    if len(xyz_all) > m:  # the context's own voxels are not sought
        mine = np.zeros(q, bool)
        mine[coarse[:m]] = True
        asked &= mine
    ask = np.flatnonzero(asked)
    cov = _neighbourhood_covariance(centre, at[ask], radius, max_neighbours)
    w = symmetric_eigenvalues3(cov)
    axis[ask] = eigenvector3(cov, w[:, 0])
    w = np.maximum(w, 0.0)
    l1 = np.maximum(w[:, 0], 1e-12)
    linearity[ask], planarity[ask] = (w[:, 0] - w[:, 1]) / l1, (w[:, 1] - w[:, 2]) / l1
    roughness[ask] = np.sqrt(w[:, 2])
    coarse = coarse[:m]
    return LocalShape(linearity[coarse], planarity[coarse], axis[coarse], roughness[coarse])


def _neighbourhood_covariance(centre: np.ndarray, query: np.ndarray, radius: float,
                              max_neighbours: int) -> np.ndarray:
    """(Q, 3, 3) m^2: the covariance of the neighbourhood of each of the (Q, 3) query
    points (m): the points `centre` (V >= 3, 3) m within `radius` m of it, at most the
    `max_neighbours` nearest."""
    v = len(centre)
    k = min(max_neighbours, v)
    dist, nn = tree_query(search_tree(centre), query, k=k, distance_upper_bound=radius,
                          workers=_workers(len(query), k))
    inside = np.isfinite(dist)
    count = inside.sum(axis=1).astype(np.float64)
    # Neighbourhood sums of 1, x, y, z and the six products in one sparse product
    # (adjacency @ moments): ~5 x faster than gathering (q, k, 3) neighbour arrays.
    # Built as CSR directly (each row's neighbours are distinct): converting from
    # coordinates sorted and summed them, ~3 ms per 50 000-point message.
    indptr = np.concatenate([[0], np.cumsum(count.astype(np.int64))])
    adjacency = csr_matrix((np.ones(int(indptr[-1])), nn[inside], indptr),
                           shape=(len(query), v))
    c = centre - column_mean(centre)  # small numbers: the products keep their precision
    pairs = [(a, b) for a in range(3) for b in range(a, 3)]
    sums = adjacency @ np.column_stack([c] + [c[:, a] * c[:, b] for a, b in pairs])
    mean = sums[:, :3] / count[:, None]
    cov = np.empty((len(query), 3, 3))
    for j, (a, b) in enumerate(pairs):
        cov[:, a, b] = cov[:, b, a] = sums[:, 3 + j] / count - mean[:, a] * mean[:, b]
    return cov


def shape_context(recent: list[np.ndarray], cloud_xy: np.ndarray, radius: float
                  ) -> np.ndarray | None:
    """(C, 3) m: the points of earlier messages, `recent` (each (R, 3) m), that lie beyond
    the edge of a thin cloud's footprint, within `radius` m of it; None when the cloud
    (cloud_xy (N, 2) m) is not thin or nothing lies there.

    A survey sliced into 0.1 s messages (las2bag) comes as strips ~5 m wide: most of a
    strip lies within a shape neighbourhood of its edge, and a roof cut there looked rough
    or linear (AHN4 streamed: 18 % of building points taken for vegetation, 4 % for wire
    or tower). The strips before it complete those neighbourhoods. The footprint is the
    cloud's occupied 1 m columns, closed and with its holes filled; it is thin when
    THIN_SHARE of it lies within `radius` of its edge. A UAV's wide scan (the simulator's
    ~30 x 85 m) is not thin: it has its own neighbourhoods, and its earlier scans, which
    it mostly covers again, are not searched (that cost ~20 ms per forest message)."""
    if not recent or len(cloud_xy) == 0:
        return None
    pad = int(np.ceil(radius)) + 2  # cells of margin around the footprint
    base = np.floor(column_min(cloud_xy)) - pad
    ij = (cloud_xy - base).astype(np.int64)
    size = tuple(int(n) for n in column_max(ij) + pad + 1)
    foot = np.zeros(size, bool)
    foot[ij[:, 0], ij[:, 1]] = True
    foot = ndimage.binary_fill_holes(ndimage.binary_closing(foot, np.ones((3, 3), bool)))
    if np.mean(ndimage.distance_transform_edt(foot)[foot] <= radius) < THIN_SHARE:
        return None
    # beyond the footprint, within radius of it (+ a cell's diagonal: cells, not points)
    band = ~foot & (ndimage.distance_transform_edt(~foot) <= radius + np.sqrt(2.0))
    lo, hi = base, base + np.array(size)
    parts = []
    for pts in recent:
        pts = pts[all_columns((pts[:, :2] >= lo) & (pts[:, :2] < hi))]
        cell = (pts[:, :2] - base).astype(np.int64)
        parts.append(pts[band[cell[:, 0], cell[:, 1]]])
    context = np.concatenate(parts)
    return context if len(context) else None


def _occupied_neighbours(ijk: np.ndarray) -> np.ndarray:
    """(V,) int: how many of the 26 voxels around each of the V distinct voxels (V, 3)
    (non-negative integer indices) are among them. On a dense grid of the voxels' box
    (~1.5 ms for a 50 000-point strip's 14 000 voxels), or, for a box of more than
    DENSE_GRID_CELLS (a whole survey tile), by searching the 26 offsets' keys."""
    span = column_max(ijk) + 3  # one empty voxel of margin on each side
    cells = int(span[0]) * int(span[1]) * int(span[2])
    if cells <= DENSE_GRID_CELLS:
        grid = np.zeros(tuple(int(s) for s in span), np.uint8)
        at = tuple(ijk[:, a] + 1 for a in range(3))
        grid[at] = 1
        for a in range(3):  # 3 x 3 x 3 box sums, one axis at a time
            lower, upper = [slice(None)] * 3, [slice(None)] * 3
            lower[a], upper[a] = slice(None, -1), slice(1, None)
            summed = grid.copy()
            summed[tuple(upper)] += grid[tuple(lower)]
            summed[tuple(lower)] += grid[tuple(upper)]
            grid = summed
        return grid[at].astype(np.int64) - 1
    key = ((ijk[:, 0] + 1) * span[1] + ijk[:, 1] + 1) * span[2] + ijk[:, 2] + 1
    order = np.sort(key)
    count = np.zeros(len(key), np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx or dy or dz:
                    near = key + (dx * span[1] + dy) * span[2] + dz
                    pos = np.minimum(np.searchsorted(order, near), len(order) - 1)
                    count += order[pos] == near
    return count


def _isolated(pts: np.ndarray, radius: float, min_neighbours: int) -> np.ndarray:
    """(M,) bool: points of (M, 3) pts (m) with fewer than `min_neighbours` others within
    `radius` m. Points of a voxel of edge radius / sqrt(3) are all within radius of each
    other, so a voxel holding more than `min_neighbours` points settles its points without
    a search; only the rest are queried (~1 ms per 50 000-point message, against 4.8 ms
    querying them all). The k nearest within the radius, not a ball count: a 3 m ball in a
    crown holds hundreds of points and counting them all cost ~7 x more."""
    isolated = np.zeros(len(pts), bool)
    if min_neighbours <= 0 or len(pts) == 0:
        return isolated
    edge = radius / np.sqrt(3.0) * (1.0 - 1e-9)  # the voxel's diagonal stays inside radius
    voxel, count, _ = _voxel_ids(np.floor(pts / edge).astype(np.int64))
    ask = np.flatnonzero(count[voxel] <= min_neighbours)
    if len(ask):
        dist, _ = tree_query(search_tree(pts), pts[ask], k=min_neighbours + 1,
                             distance_upper_bound=radius, workers=_workers(len(ask)))
        isolated[ask] = ~np.isfinite(dist.reshape(len(ask), -1)[:, -1])
    return isolated


def _voxel_ids(ints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For (M, 3) integer voxel indices: the voxel (M,) of each point, numbered as
    np.unique(axis=0) numbers the rows (x, then y, then z), the points per voxel (V,) and
    each voxel's index (V, 3)."""
    base = column_min(ints)
    rel = ints - base
    span = column_max(rel) + 1
    keys, voxel = unique_ints((rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2],
                              table_ratio=8.0)
    index = np.column_stack([keys // (span[1] * span[2]), keys // span[2] % span[1],
                             keys % span[2]]) + base
    return voxel, np.bincount(voxel), index


def _voxel_grid(
        xyz: np.ndarray, lo: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids (V, 3) of the occupied voxels of edge `edge` m counted from `lo`, the
    voxel (M,) of each point and the integer index (V, 3) of each voxel."""
    ints = cell_index(xyz - lo, edge)  # (a point on a voxel's edge: see cell_index)
    voxel, count, index = _voxel_ids(ints)
    return (np.stack([np.bincount(voxel, xyz[:, a]) for a in range(3)], axis=1)
            / count[:, None], voxel, index)


def _voxel_centroids(xyz: np.ndarray, lo: np.ndarray, edge: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (V, 3) of the occupied voxels of edge `edge` m counted from `lo`, and the
    voxel (M,) of each point."""
    centroids, voxel, _ = _voxel_grid(xyz, lo, edge)
    return centroids, voxel


def voxel_components(xyz: np.ndarray, size: float) -> np.ndarray:
    """(M,) int labels of (M, 3) points xyz (m): connected components of the occupied
    voxels of edge `size` m (26-neighbourhood), numbered in the order of their first voxel
    (x, then y, then z). On a dense grid of the
    voxels' box (2-5 x faster: a forest strip's 45 000 points 2-3 ms instead of 4-13 ms),
    or, for a box of more than DENSE_GRID_CELLS, on a graph of the occupied voxels."""
    m = len(xyz)
    if m == 0:
        return np.zeros(0, np.int64)
    ijk = cell_index(xyz - column_min(xyz), size) + 1
    dims = column_max(ijk) + 2
    if int(dims[0]) * int(dims[1]) * int(dims[2]) <= DENSE_GRID_CELLS:
        grid = np.zeros(tuple(int(d) for d in dims), bool)
        at = (ijk[:, 0], ijk[:, 1], ijk[:, 2])
        grid[at] = True
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
        return labels[at].astype(np.int64) - 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    vox, inv = np.unique(key, return_inverse=True)
    rows, cols = [], []
    offsets = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                        if (a, b, c) > (0, 0, 0)])
    vijk = np.column_stack([vox // (dims[1] * dims[2]), (vox // dims[2]) % dims[1],
                            vox % dims[2]])
    for off in offsets:
        nkey = (((vijk[:, 0] + off[0]) * dims[1] + vijk[:, 1] + off[1]) * dims[2]
                + vijk[:, 2] + off[2])
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
    # Only points inside the candidates' box (1 m around, WIRE_GAP below) can block: the
    # tree is built on those (on a forest strip most of the crowns lie elsewhere).
    c, o = xyz[cand], xyz[others]
    lo, hi = column_min(c), column_max(c)
    near = ((o[:, 0] >= lo[0] - 1.0) & (o[:, 0] <= hi[0] + 1.0)
            & (o[:, 1] >= lo[1] - 1.0) & (o[:, 1] <= hi[1] + 1.0)
            & (o[:, 2] > lo[2] - WIRE_GAP) & (o[:, 2] < hi[2] - 0.5))
    others = others[near]
    if len(others) == 0:
        return ok
    owner, idx = neighbour_pairs(xyz[cand, :2], xyz[others, :2], 1.0)
    if len(owner) == 0:
        return ok
    dz = xyz[cand[owner], 2] - xyz[others[idx], 2]
    blocked = (dz > 0.5) & (dz < WIRE_GAP)
    ok[np.unique(owner[blocked])] = False
    return ok


def _label_stats(labels: np.ndarray, xyz: np.ndarray, hag: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per label 0..L-1 of (M,) labels: point count, horizontal diagonal of the box (m) and
    highest height above ground (m)."""
    n_labels = int(labels.max()) + 1 if len(labels) else 0
    count = np.bincount(labels, minlength=n_labels)
    lo = np.full((n_labels, 2), np.inf)
    hi = np.full((n_labels, 2), -np.inf)
    for a in range(2):
        np.minimum.at(lo[:, a], labels, xyz[:, a])
        np.maximum.at(hi[:, a], labels, xyz[:, a])
    top = np.full(n_labels, -np.inf)
    np.maximum.at(top, labels, hag)
    return count, row_norm(hi - lo), top


def _wires(xyz: np.ndarray, cand: np.ndarray, hag: np.ndarray, shape: LocalShape,
           cfg: ObstaclesConfig, known: np.ndarray) -> np.ndarray:
    """(M,) bool over the candidates `cand`: linear, near-horizontal points high above ground
    with empty space below, joined into runs of at least WIRE_MIN_RUN metres, counting the
    wire points `known` (K, 3) m from earlier messages that they continue."""
    wire_like = ((shape.linearity > cfg.wire_linearity)
                 & (np.abs(shape.axis[:, 2]) < np.sin(np.radians(cfg.wire_max_slope)))
                 & (hag[cand] > cfg.wire_min_clearance))
    wl = np.flatnonzero(wire_like)
    wl = wl[_empty_below(xyz, cand[wl], cand[~wire_like])]
    is_wire = np.zeros(len(cand), bool)
    if len(wl):
        pts = xyz[cand[wl]]
        if len(known):
            # enough of the known wire to make up a run (its far parts change nothing)
            lo, hi = column_min(pts) - WIRE_MIN_RUN, column_max(pts) + WIRE_MIN_RUN
            pts = np.concatenate([pts, known[all_columns((known >= lo) & (known <= hi))]])
        runs = voxel_components(pts, WIRE_LINK)
        _, length, _ = _label_stats(runs, pts, np.zeros(len(pts)))
        ok = (length >= WIRE_MIN_RUN) & _seeds_run_one_way(runs, pts, shape.axis[wl])
        is_wire[wl[ok[runs[:len(wl)]]]] = True
    return is_wire


def _on_known_roofs(pts: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(P,) bool: which of the points pts (P, 3) m lie within ROOF_WIRE_REACH of a roof or
    wall of an earlier message (known (B, 4), `_buildings`' rows). A survey's 0.1 s strip
    across a flat roof is a few scan lines wide, linear and level: the wire test passed
    it, and such "wires" beside a wall then made the building a tower (AHN4 streamed: 139
    roof points wire, 389 tower). A wire that touches a roof is not one a UAV flies
    under."""
    roofs = known[known[:, 3] > 0, :3]
    roofs = _in_box(roofs, column_min(pts) - ROOF_WIRE_REACH,
                    column_max(pts) + ROOF_WIRE_REACH)
    if len(roofs) == 0:
        return np.zeros(len(pts), bool)
    dist, _ = search_tree(roofs).query(pts, distance_upper_bound=ROOF_WIRE_REACH)
    return np.isfinite(dist)


def _seeds_run_one_way(runs: np.ndarray, pts: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(L,) bool per run label: a run may be a wire. runs (P,) labels of pts (P, 3) m, the
    M wire candidates of this message first, then known wire points; axis (M, 3) the
    candidates' main axes. A run holding a known wire point continues a wire; a new one
    seen in fewer than SEED_VOXELS voxels needs its candidates' axes to agree in azimuth
    to SEED_AGREEMENT. In a dense forest a few scattered crown points a message pass the
    wire test, and a 4 m link joins 3-7 of them across 10 m into a run: their axes point
    anywhere (agreement 0.19-0.90 on the simulated forests), while the smallest new wires
    of the AHN corridor tiles, whole and streamed (8-14 voxels, two or three conductors
    side by side), agree to 0.97 and more. Once taken, such a crown "wire" was remembered
    and continued message after message."""
    m = len(axis)
    n_labels = int(runs.max()) + 1
    known = np.zeros(n_labels, bool)
    known[runs[m:]] = True
    mine = runs[:m]
    cells = cell_index(pts[:m] - column_min(pts[:m]), WIRE_MEMORY_VOXEL)
    span = column_max(cells) + 1
    key = (mine * span[0] + cells[:, 0]) * span[1] + cells[:, 1]
    key = key * span[2] + cells[:, 2]
    voxels = np.bincount(np.unique(key) // int(span[0] * span[1] * span[2]), minlength=n_labels)
    angle = 2.0 * np.arctan2(axis[:, 1], axis[:, 0])  # axial: a line's two directions agree
    count = np.maximum(np.bincount(mine, minlength=n_labels), 1)
    agreement = np.hypot(np.bincount(mine, np.cos(angle), n_labels),
                         np.bincount(mine, np.sin(angle), n_labels)) / count
    return known | (voxels >= SEED_VOXELS) | (agreement >= SEED_AGREEMENT)


def _off_line(p: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(K,) distance (m) of points p (K, 3) from the lines through origin (K, 3) along the
    unit axis (K, 3)."""
    d = p - origin
    along = d[:, 0] * axis[:, 0] + d[:, 1] * axis[:, 1] + d[:, 2] * axis[:, 2]
    return row_norm(d - along[:, None] * axis)


def _supported_wires(known: np.ndarray | None) -> np.ndarray:
    """(S, 3) m: the rows of known wire (W, 4) (x, y, z, 1 if it passed the wire test
    itself; (W, 3): all did) that have SEED_VOXELS tested rows within KNOWN_WIRE_SUPPORT
    m, themselves included."""
    if known is None or len(known) == 0:
        return np.zeros((0, 3))
    known = np.asarray(known, float)
    if known.shape[1] == 3:
        return known
    # Voxels, not rows: a wire scanned again and again is remembered many times over (a
    # simulated corridor's memory: 9 500 rows), and each copy would count.
    centroids, voxel = _voxel_centroids(known[:, :3], column_min(known[:, :3]),
                                        WIRE_MEMORY_VOXEL)
    tested = centroids[np.bincount(voxel, known[:, 3] > 0, len(centroids)) > 0]
    if len(tested) < SEED_VOXELS:
        return np.zeros((0, 3))
    # the SEED_VOXELS-th nearest tested voxel within reach, not a count of them all
    dist, _ = tree_query(search_tree(tested), centroids, k=SEED_VOXELS,
                         distance_upper_bound=KNOWN_WIRE_SUPPORT,
                         workers=_workers(len(centroids), SEED_VOXELS))
    return known[np.isfinite(dist[:, -1])[voxel], :3]


def _known_wire_seeds(known: np.ndarray, pts: np.ndarray, found: np.ndarray,
                      cfg: ObstaclesConfig) -> tuple[np.ndarray, np.ndarray]:
    """The wire points `known` (K, 3) m of earlier messages from which a wire may be
    followed into the points pts (P, 3) m, and their lines' unit axes, as two (S, 3)
    arrays: one per WIRE_MEMORY_VOXEL voxel of the known wire within KNOWN_WIRE_REACH of
    a point of pts but not within WIRE_STEP of this message's own wire points `found`
    (F, 3) (from which it is followed anyway), whose known wire within
    KNOWN_WIRE_AXIS_REACH lies on a line (linearity above cfg.wire_linearity, no steeper
    than cfg.wire_max_slope). A survey's 0.1 s strip may hold a piece of wire only where
    it passes through a crown: nothing there is linear, so nothing of this message starts
    the following, but the wire found in the strips before leads in (the corridor tile
    07CZ2_14 streamed: 627 of 16 312 wire points were vegetation). Voxels, not the
    known points: a UAV that scans a wire again and again remembers each piece many
    times over (the simulated corridor: ~100 copies)."""
    none = np.zeros((0, 3))
    if len(known) == 0 or len(pts) == 0:
        return none, none
    lo, hi = column_min(pts), column_max(pts)
    reach = KNOWN_WIRE_REACH + KNOWN_WIRE_AXIS_REACH
    known = known[all_columns((known >= lo - reach) & (known <= hi + reach))]
    if len(known) < 3:
        return none, none
    known, _ = _voxel_centroids(known, column_min(known), WIRE_MEMORY_VOXEL)
    seeds = known
    if len(found):  # (first: a UAV sees again most of the wire it knows)
        dist, _ = search_tree(found).query(seeds, distance_upper_bound=WIRE_STEP)
        seeds = seeds[~np.isfinite(dist)]
    if len(seeds):
        dist, _ = search_tree(pts).query(seeds, distance_upper_bound=KNOWN_WIRE_REACH)
        seeds = seeds[np.isfinite(dist)]
    if len(seeds) == 0:
        return none, none
    i, j = neighbour_pairs(seeds, known, KNOWN_WIRE_AXIS_REACH)
    d = known[j] - seeds[i]  # centred on the seed: survey coordinates keep their precision
    count = np.maximum(np.bincount(i, minlength=len(seeds)), 1).astype(np.float64)
    # (float: weighted counts; the type stubs say a count is an integer)
    mean: np.ndarray = np.column_stack([np.bincount(i, d[:, a], len(seeds)) for a in range(3)])
    mean /= count[:, None]
    cov = np.empty((len(seeds), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = (np.bincount(i, d[:, a] * d[:, b], len(seeds))
                                           / count - mean[:, a] * mean[:, b])
    values = np.maximum(symmetric_eigenvalues3(cov), 0.0)
    axis = eigenvector3(cov, values[:, 0])
    linear = ((values[:, 0] - values[:, 1]) / np.maximum(values[:, 0], 1e-12)
              > cfg.wire_linearity)
    ok = (linear & (count >= 3)
          & (np.abs(axis[:, 2]) < np.sin(np.radians(cfg.wire_max_slope))))
    return seeds[ok], axis[ok]


def _follow_wires(pts: np.ndarray, allowed: np.ndarray, axis: np.ndarray,
                  is_wire: np.ndarray, seeds: np.ndarray | None = None,
                  seed_axis: np.ndarray | None = None) -> None:
    """Grow `is_wire` (M,) in place: an allowed point within WIRE_STEP of a wire point and
    within WIRE_TUBE of that wire point's line is wire too. A wire through a crown is no
    longer linear in its neighbourhood (the leaves around it are not), but it stays on its
    line; ~1.5 m per round, so a 15 m crown takes 10 rounds. A followed point carries on the
    axis of the wire point it was followed from and the origin of the known wire where the
    chain began: the chain may bend with the sag, but not drift leaf by leaf more than
    WIRE_DRIFT from that wire's line.

    seeds (S, 3) m with their unit axes (S, 3): wire points of earlier messages
    (`_known_wire_seeds`) from which the first step reaches KNOWN_WIRE_REACH: a strip's
    first point on a wire may lie that far from the last the strip before it saw. That
    step's tube is wider by half a WIRE_MEMORY_VOXEL: a seed is the centroid of a voxel,
    which two conductors 0.5 m apart may share (then it lies between them)."""
    m = len(pts)
    grown = is_wire
    if seeds is not None and len(seeds):
        pts = np.concatenate([pts, seeds])
        allowed = np.concatenate([allowed, np.zeros(len(seeds), bool)])
        axis = np.concatenate([axis, seed_axis])
        grown = np.concatenate([is_wire, np.ones(len(seeds), bool)])
    origin = pts.copy()
    line_axis = axis.copy()

    def step(front: np.ndarray, reach: float, tube: float = WIRE_TUBE) -> np.ndarray:
        """The points the wire points `front` take on (marked in `grown`)."""
        free = np.flatnonzero(allowed & ~grown)
        if len(free) == 0 or len(front) == 0:
            return free[:0]
        owner, src = neighbour_pairs(pts[free], pts[front], reach)
        owner, src = free[owner], front[src]
        perp = _off_line(pts[owner], pts[src], line_axis[src])
        ok = (perp < tube) & (_off_line(pts[owner], origin[src], line_axis[src])
                              < WIRE_DRIFT)
        # each new point joins the line it lies closest to
        best = np.lexsort((perp[ok], owner[ok]))
        first = np.ones(len(best), bool)
        first[1:] = owner[ok][best[1:]] != owner[ok][best[:-1]]
        new, via = owner[ok][best[first]], src[ok][best[first]]
        grown[new] = True
        origin[new], line_axis[new] = origin[via], line_axis[via]
        return new

    front = np.flatnonzero(grown[:m])
    if len(pts) > m:
        front = np.concatenate([front, step(np.arange(m, len(pts)), KNOWN_WIRE_REACH,
                                            WIRE_TUBE + WIRE_MEMORY_VOXEL / 2.0)])
    for _ in range(WIRE_FOLLOW_ROUNDS):
        front = step(front, WIRE_STEP)
        if len(front) == 0:
            break
    is_wire[:] = grown[:m]


def patch_area(pts: np.ndarray, labels: np.ndarray, cell: float = 1.0) -> np.ndarray:
    """(L,) area in m^2 of each patch of (M, 3) points labelled 0..L-1: occupied cells of
    `cell` m in the patch's own plane (its two main axes), so a wall counts as much as a
    roof of the same size (its footprint on the map is a thin line)."""
    n_labels = int(labels.max()) + 1
    count = np.bincount(labels, minlength=n_labels).astype(np.float64)
    mean: np.ndarray = np.stack([np.bincount(labels, pts[:, a], n_labels) for a in range(3)],
                                axis=1)  # (float: weighted counts)
    mean /= np.maximum(count, 1)[:, None]
    rel = pts - mean[labels]
    cov = np.empty((n_labels, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(labels, rel[:, a] * rel[:, b], n_labels)
    _, axis, normal = symmetric_eig3(cov)
    second = np.cross(normal, axis)
    uv = np.floor(np.column_stack([(rel * axis[labels]).sum(axis=1),
                                   (rel * second[labels]).sum(axis=1)]) / cell).astype(np.int64)
    uv -= column_min(uv)
    per_label = int(uv[:, 0].max() + 1) * int(uv[:, 1].max() + 1)
    cells = np.unique((labels * per_label + uv[:, 0] * int(uv[:, 1].max() + 1) + uv[:, 1]))
    return np.bincount(cells // per_label, minlength=n_labels) * cell ** 2


def quadric_fit(xyz: np.ndarray, threshold: float, rounds: int = 5
                ) -> tuple[np.ndarray, np.ndarray]:
    """The quadric surface (ax² + by² + cz² + dxy + exz + fyz + gx + hy + iz + j = 0:
    spheres, cylinders, cones, paraboloids, saddles and planes) nearest to (N, 3) points
    (m), and per point its distance (N,) m and unit normal (N, 3) there.

    The algebraic least-squares fit (the coefficients the smallest eigenvector of the
    monomials' scatter matrix, in coordinates centred and scaled to unit RMS radius so
    that all ten weigh alike), refitted `rounds` - 1 times on the points within
    2 x `threshold` m of the last fit, so that a wall joined to a vault does not bend it
    (a vault of radius 8 m and its gable wall, a fifth of the points: 3 fits hold 65 %
    of the vault, 5 fits 85 %; a tenth: 91 and 100 %). Fitted on QUADRIC_SAMPLE points
    at most, taken evenly through the array (a 3 500 m² vault's 26 000 points: 17 ms
    all, 4 ms so). The distance is Sampson's first-order one, |f| / |grad f|: exact on
    a plane; points up to 0.1 m off a sphere of radius 10 m or a cylinder of radius 5 m
    measure within 0.02 m of their offsets. A plane is a degenerate quadric: every pair
    of planes holding it fits a flat patch, and the distances near their crossing are
    meaningless (flat patches are the plane test's, `_buildings`). Fewer than 10 points:
    every distance infinite."""
    n = len(xyz)
    if n < 10:
        return np.full(n, np.inf), np.tile([0.0, 0.0, 1.0], (n, 1))
    rel = xyz - column_mean(xyz)
    scale = max(float(np.sqrt(np.mean(rel[:, 0] ** 2 + rel[:, 1] ** 2 + rel[:, 2] ** 2))),
                1e-9)
    rel /= scale

    def monomials(q: np.ndarray) -> np.ndarray:
        x, y, z = q[:, 0], q[:, 1], q[:, 2]
        return np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z,
                                np.ones(len(q))])

    def distance(q: np.ndarray, m: np.ndarray, c: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        x, y, z = q[:, 0], q[:, 1], q[:, 2]
        grad = np.column_stack([2 * c[0] * x + c[3] * y + c[4] * z + c[6],
                                2 * c[1] * y + c[3] * x + c[5] * z + c[7],
                                2 * c[2] * z + c[4] * x + c[5] * y + c[8]])
        norm = np.maximum(row_norm(grad), 1e-12)
        return np.abs(m @ c) / norm * scale, grad / norm[:, None]

    sample = rel[::max(1, n // QUADRIC_SAMPLE)]
    m = monomials(sample)
    fit = np.ones(len(sample), bool)
    for _ in range(rounds):
        c = np.linalg.eigh(m[fit].T @ m[fit])[1][:, 0]
        near = distance(sample, m, c)[0] < 2.0 * threshold
        if near.sum() < 10:
            break
        fit = near
    return distance(rel, monomials(rel), c)


def solid_share(pts: np.ndarray, cell: float = 1.0) -> float:
    """Share of the occupied cells (edge `cell` m) of (N, 3) points, in their own plane
    (their two main axes, as `patch_area`), whose 8 neighbours are all occupied: near 1
    for a solid sheet, small for a lacy one (or a strip a few cells wide)."""
    rel = pts - column_mean(pts)
    cov = rel.T @ rel
    axes = np.linalg.eigh(cov)[1][:, 1:]  # the two largest
    uv = cell_index(rel @ axes - column_min(rel @ axes), cell) + 1
    width = int(uv[:, 1].max()) + 2
    keys = np.unique(uv[:, 0] * width + uv[:, 1])
    inside = np.ones(len(keys), bool)
    for du in (-1, 0, 1):
        for dv in (-1, 0, 1):
            if du or dv:
                nb = keys + du * width + dv
                pos = np.minimum(np.searchsorted(keys, nb), len(keys) - 1)
                inside &= keys[pos] == nb
    return float(inside.mean())


def _curved_roof(pts: np.ndarray, hag: np.ndarray, on_plane: np.ndarray,
                 rough: np.ndarray, lo: np.ndarray, threshold: float) -> bool:
    """Whether a smooth patch of (N, 3) points (m; hag (N,) m above ground) that its main
    plane (on_plane (N,) bool) does not hold is a curved roof or wall: a vault, a dome,
    a silo. rough: (R, 3) m, the rough candidate points (lo (3,) m: the corner of the
    patches' 1 m voxel grid). Four tests, each against what else is smooth and curved:

    - one quadric surface (`quadric_fit`), with the main plane (a gable wall joined to a
      vault), holds CURVED_SHARE of it within `threshold`: a surface, not a heap of
      smooth bits;
    - it is a solid sheet, CURVED_SOLID of its cells inside it: in a crown the smooth
      patches are lacy, broken by the rough leaves between them;
    - its voxels hold at most CURVED_ROUGH rough points (roughness over `threshold`,
      against its own): a crown's smooth top has rough foliage in and under it;
    - where it comes within CURVED_FOOT of the ground it is steep (a Quonset's springing,
      a wall): a heap of earth or gravel, or terrain the ground filter left out, rises
      from the ground on gentle flanks.

    On synthetic vaults, domes and arcs scanned 0.3-0.5 m apart the roofs hold 0.94-1.00
    of their points on the quadric and its plane, are 0.62-0.92 solid and at most 1.5 %
    rough; the smooth patches of synthetic crowns are 0-0.55 solid and 0.6-24 % rough.
    The mound and the cone of test_obstacles.py fail only the last test. On sparse scans
    (about a point per m², the ISPRS samples) most 1 m cells are empty and no patch is
    solid: no curved roof is found there."""
    dist, normal = quadric_fit(pts, threshold)
    on = dist < threshold
    if (on | on_plane).mean() < CURVED_SHARE or solid_share(pts) < CURVED_SOLID:
        return False
    low = on & (hag < CURVED_FOOT)
    if low.any() and np.median(np.abs(normal[low, 2])) > CURVED_FOOT_NZ:
        return False
    vox = cell_index(pts - lo, 1.0)
    box_lo, box_hi = column_min(vox), column_max(vox)
    r = cell_index(rough - lo, 1.0)
    r = r[all_columns((r >= box_lo) & (r <= box_hi))] - box_lo
    if len(r) == 0:
        return True
    span = box_hi - box_lo + 1
    own = np.unique(((vox[:, 0] - box_lo[0]) * span[1] + vox[:, 1] - box_lo[1]) * span[2]
                    + vox[:, 2] - box_lo[2])
    among = np.isin((r[:, 0] * span[1] + r[:, 1]) * span[2] + r[:, 2], own).sum()
    return bool(among <= CURVED_ROUGH * (len(pts) + among))


def _plane_pieces(pts: np.ndarray, first: np.ndarray, first_normal: np.ndarray,
                  threshold: float, rng: np.random.Generator) -> bool:
    """Whether a patch of (P, 3) points (m) whose main plane (normal (3,), inliers first
    (P,) bool) holds too few of them is a house seen whole: RANSAC planes found one after
    another on what the earlier ones leave, each holding PIECE_SHARE of the patch or more
    (at most MAX_PIECES), hold PIECES_SHARE of it together, and one of them is a wall
    (its normal within WALL_TILT of horizontal). Its roof planes, walls and gables are one
    smooth patch with no plane of PLANAR_SHARE: the demo's first message (planes 0.39,
    0.23, ...) and a simulated urban one (0.38, 0.35) lost their roofs to high
    vegetation; with walls 6 m high the roof planes hold ~0.2 each. A smooth mound or a
    cone of gravel is cut into bands of planes as well, but none is a wall. No patch of
    the AHN files comes to this test (their main planes hold 0.4 or more)."""
    left = ~first
    held = float(first.mean())
    wall = abs(float(first_normal[2])) <= np.sin(np.radians(WALL_TILT))
    for _ in range(MAX_PIECES - 1):
        if (held >= PIECES_SHARE and wall) or np.count_nonzero(left) < 3:
            break
        idx = np.flatnonzero(left)
        piece = ransac_plane(pts[idx], distance_threshold=threshold, max_trials=100, rng=rng)
        share = np.count_nonzero(piece.inliers) / len(pts)
        if piece.plane is None or share < PIECE_SHARE:
            break
        left[idx[piece.inliers]] = False
        held += share
        wall |= abs(float(piece.plane.normal[2])) <= np.sin(np.radians(WALL_TILT))
    return held >= PIECES_SHARE and wall


def _buildings(xyz: np.ndarray, cand: np.ndarray, shape: LocalShape, allowed: np.ndarray,
               cfg: ObstaclesConfig, rng: np.random.Generator, known: np.ndarray,
               hag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool over the candidates `cand`: roofs and walls with what clings to them, and
    (M,) bool: the roofs and walls alone.

    Smooth planar points (points within +-t of a plane spread t/sqrt(3), t the plane
    threshold) are joined into patches on a 1 m voxel grid, with the building points
    `known` (K, 4) (x, y, z m and the roof-or-wall flag) from earlier messages that they
    continue; a patch covering at least `building_min_area` whose main plane, found by the
    paper's RANSAC with the robust eigenvalue fit, holds PLANAR_SHARE of this message's
    part of it is a roof or wall. A patch no plane holds that much of (a barrel vault of
    radius 10 m: 24 % on its main plane, a hemispherical dome 6 %) is a curved roof or
    wall when `_curved_roof` says so; hag: (M,) m, the candidates' height above ground.
    Crowns are rough, so their patches stay small, and what smooth patches they have are
    lacy among rough foliage (`_curved_roof`). Edges,
    ridges and chimneys are rough too: the allowed points within BUILDING_REACH of a roof
    or wall, of this message or a known one, join it. Only roofs and walls draw them in:
    had what clung to a known building drawn more, at 10 Hz a building would have grown
    into the trees beside it by 1.5 m a message (simulated urban flight: 11 % of the
    vegetation became building)."""
    is_building = np.zeros(len(cand), bool)
    smooth = np.flatnonzero(allowed & (shape.planarity > BUILDING_PLANARITY)
                            & (shape.roughness < cfg.building_plane_threshold / np.sqrt(3.0)))
    if len(smooth) >= 3:
        pts = xyz[cand[smooth]]
        if len(known):  # what can join them: within a voxel and its neighbours
            lo, hi = column_min(pts) - 2.0, column_max(pts) + 2.0
            pts = np.concatenate([pts, _in_box(known[:, :3], lo, hi)])
        lo = column_min(pts)  # the patches' voxel grid
        patches = voxel_components(pts, 1.0)
        area = patch_area(pts, patches)
        patches = patches[:len(smooth)]
        counts = np.bincount(patches, minlength=len(area))
        big = np.flatnonzero((area >= cfg.building_min_area) & (counts >= 3))
        order = np.argsort(patches, kind="stable")
        starts = np.searchsorted(patches[order], big)
        rough = None
        for lab, st in zip(big, starts):
            members = smooth[order[st:st + counts[lab]]]
            plane = ransac_plane(xyz[cand[members]],
                                 distance_threshold=cfg.building_plane_threshold,
                                 max_trials=100, rng=rng)
            if plane.plane is not None and (
                    plane.inliers.mean() >= PLANAR_SHARE
                    or _plane_pieces(xyz[cand[members]], plane.inliers, plane.plane.normal,
                                     cfg.building_plane_threshold, rng)):
                is_building[members] = True
                continue
            if rough is None:  # only a patch no plane holds needs them (few messages)
                rough = xyz[cand[allowed & (shape.roughness > cfg.building_plane_threshold)]]
            is_building[members] = _curved_roof(xyz[cand[members]], hag[members],
                                                plane.inliers, rough, lo,
                                                cfg.building_plane_threshold)
    roofs = is_building.copy()
    others = np.flatnonzero(allowed & ~is_building)
    if len(others) == 0:
        return is_building, roofs
    pull = xyz[cand[is_building]]
    if len(known):
        near = xyz[cand[others]]
        lo, hi = column_min(near) - BUILDING_REACH, column_max(near) + BUILDING_REACH
        pull = np.concatenate([pull, _in_box(known[known[:, 3] > 0, :3], lo, hi)])
    if len(pull):
        dist, _ = tree_query(search_tree(pull), xyz[cand[others]],
                             distance_upper_bound=BUILDING_REACH, workers=_workers(len(others)))
        is_building[others[np.isfinite(dist)]] = True
    return is_building, roofs


def _in_box(pts: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The rows of (K, 3) pts within the box lo..hi (3,)."""
    return pts[all_columns((pts >= lo) & (pts <= hi))]


class _WireDirections:
    """The direction on the map of the wires (W, 3) m at each of their points, in whole
    degrees 0-179 (-1: none), from the centroids of their WIRE_MEMORY_VOXEL voxels (on a
    wire, on its line), each voxel's worked out when first asked for: a message asks for
    those round the few objects the wires say no to. Voxels, not points: on the simulated
    mixed flight, whose UAV scans wires densely, the points cost 68 ms for one object's
    ring of wire, the voxels (made once a message) 6 ms."""

    def __init__(self, wire_xyz: np.ndarray) -> None:
        self.xyz = wire_xyz
        self.voxel: np.ndarray | None = None

    def _voxels(self) -> np.ndarray:
        """(W,) the voxel of each wire point, the voxels' centroids and tree made the first
        time they are needed."""
        if self.voxel is None:
            self.centroids, self.voxel = _voxel_centroids(self.xyz, column_min(self.xyz),
                                                          WIRE_MEMORY_VOXEL)
            self.tree = search_tree(self.centroids)
            self.degree = np.full(len(self.centroids), -2)  # -2: not worked out yet
        return self.voxel

    def __call__(self, idx: np.ndarray) -> np.ndarray:
        """(C,) int: the direction at the wire points idx (C,) (indices into the wires)."""
        v = self._voxels()[idx]
        new = np.unique(v[self.degree[v] == -2])
        if len(new):
            self.degree[new] = self._directions(self.centroids[new])
        return self.degree[v]

    def length(self, idx: np.ndarray) -> float:
        """Metres of wire with a direction among the wire points idx (C,): their voxels
        that have one, WIRE_MEMORY_VOXEL each (a count the scan's density does not
        change)."""
        if len(idx) == 0:
            return 0.0
        directed = idx[self(idx) >= 0]
        return len(np.unique(self._voxels()[directed])) * WIRE_MEMORY_VOXEL

    def _directions(self, q: np.ndarray) -> np.ndarray:
        """(Q,) int degrees (-1: none) of the wire at the (Q, 3) points q (m): the main axis
        of the 2 x 2 covariance of the x, y of the voxel centroids within LINE_REACH, when
        their spread along it is at least three times that across ((l1 - l2) / (l1 + l2)
        > 0.5) and LINE_SPREAD (sqrt(l1); 0.58 m for a piece 2 m long): a lone piece, a
        vertical drop (whose few centroids' noise may line up) has none. All of them, not
        the nearest few: a bundle of sub-conductors 0.5 m apart has as many across it as
        along within a few decimetres."""
        pairs = search_tree(q).sparse_distance_matrix(self.tree, LINE_REACH,
                                                      output_type="ndarray")
        i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        # centred on the query point: survey coordinates keep their precision
        dx = self.centroids[j, 0] - q[i, 0]
        dy = self.centroids[j, 1] - q[i, 1]
        count = np.bincount(i, minlength=len(q))
        n = np.maximum(count, 1)
        mx, my = np.bincount(i, dx, len(q)) / n, np.bincount(i, dy, len(q)) / n
        cxx = np.bincount(i, dx * dx, len(q)) / n - mx * mx
        cyy = np.bincount(i, dy * dy, len(q)) / n - my * my
        cxy = np.bincount(i, dx * dy, len(q)) / n - mx * my
        # the doubled angle's vector: a wire has one direction whichever way one looks
        c2, s2 = cxx - cyy, 2.0 * cxy
        spread = np.hypot(c2, s2)  # l1 - l2
        ok = ((count >= 3) & (spread > 0.5 * (cxx + cyy))
              & (cxx + cyy + spread >= 2.0 * LINE_SPREAD ** 2))
        degree = np.round(np.degrees(np.arctan2(s2, c2) / 2.0)).astype(np.int64) % 180
        return np.where(ok, degree, -1)


def _line_filter(level: np.ndarray, directions: _WireDirections
                 ) -> Callable[..., np.ndarray] | None:
    """The wire of the lines an object stands among: own(idx, lone=True), for (C,)
    indices into the wires (those of `directions`), gives (C,) bool, False for the wire
    points running LINE_ANGLE or more off the direction of all but less than LINE_SHARE
    of the wire points `level` (L,) round the object at its own height (of those with a
    direction; about LINE_SAMPLE of them, evenly through the list, tell the shares), and
    for those without a direction unless `lone`. The conductors of one line run side by
    side, a line crossing it at an angle (a 110 kV line under a 380 kV one: 30-90
    degrees); an angle tower stands among the wires of both its spans, about half of
    them each. None: every wire counts (none round the object has a direction)."""
    degree = directions(level[::max(1, len(level) // LINE_SAMPLE)])
    degree = degree[degree >= 0]
    if len(degree) == 0:
        return None
    # the share of them within LINE_ANGLE (in whole degrees, strictly) of each degree
    w = int(LINE_ANGLE) - 1
    count = np.bincount(degree, minlength=180)
    window = np.cumsum(np.concatenate([[0], count[-w:], count, count[:w]]))
    lines = window[2 * w + 1:] - window[:180] >= LINE_SHARE * len(degree)

    def own(idx: np.ndarray, lone: bool = True) -> np.ndarray:
        d = directions(idx)
        return np.where(d >= 0, lines[d], lone)

    return own


def _wires_sag_away(top_xy: np.ndarray, top_z: float, touching: np.ndarray,
                    wire_xyz: np.ndarray, wire_xy_tree: cKDTree,
                    own: Callable[..., np.ndarray] | None = None) -> bool:
    """True when the wires sag away from an object on every side: they hang from it.

    top_xy (2,) m is the object's top on the map, top_z (m) the z of its column's highest
    point, touching (T, 3) m the wire points next to it; wire_xyz (W, 3) m the wires, and
    wire_xy_tree a tree of their x, y. A catenary is highest at its supports, so away from
    a tower its wires are lower (a 300 m span with 8 m of sag drops ~4 m in 40 m); at a
    tree under the line the wires run level or rise towards the next tower on at least one
    side (wire on one side only cannot tell them apart: then the attachment decides). The
    top wire decides (95th percentiles):
    a tower carries the highest wire, a tree touches lower ones at most. When the cloud
    holds no wire beyond SAG_NEAR (a narrow strip of a live scan) the attachment alone
    decides; when it holds wire only further than SAG_FAR, the touching pieces are no span.
    With `own` (`_line_filter`), only the wire of the object's own lines counts, and
    beyond SAG_NEAR only such wire with a direction (a lone stray point shows no span)."""
    far = np.asarray(wire_xy_tree.query_ball_point(top_xy, r=SAG_FAR), np.int64)
    d = row_norm(wire_xyz[far, :2] - top_xy)
    far = far[d > SAG_NEAR]
    if own is not None and len(far):
        far = far[own(far)]
    if len(far) < 10:
        beyond = np.flatnonzero(row_norm(wire_xyz[:, :2] - top_xy) > SAG_NEAR)
        if own is not None and len(beyond):
            beyond = beyond[own(beyond, lone=False)]
        return not len(beyond)
    rel = wire_xyz[far, :2] - top_xy
    direction = np.linalg.eigh(rel.T @ rel)[1][:, -1]
    side = rel @ direction > 0
    z_touch = float(np.percentile(touching[:, 2], 95))
    sides = [s for s in (side, ~side) if s.sum() >= 5]
    if len(sides) < 2:
        # Wire on one side only: a dead end, where the data ends, or a strip that has seen
        # the span on one side so far. A span rising to a higher tower need not sag below
        # its low end, so the attachment decides, unless the top wire there passes well
        # above both what the object touches and its own top: a tower carries its highest
        # wire at its peak, while a tree or crane reaching a lower conductor stands under
        # the higher ones (streamed 07CZ2_14: 3-4 m under, 7 000 points). A tower whose
        # peak the strip has not seen yet reaches up to its earth wire's height.
        return all(np.percentile(wire_xyz[far[s], 2], 95)
                   <= max(z_touch, top_z) + SAG_ONE_SIDE_RISE for s in sides)
    return all(np.percentile(wire_xyz[far[s], 2], 95) <= z_touch - SAG_MIN_DROP
               for s in sides)


def _tower_body(p: np.ndarray, h: np.ndarray, column: np.ndarray, top_h: float
                ) -> np.ndarray:
    """(M,) bool: the tower's own points in its object (p (M, 3) m, h (M,) m above ground,
    top_h its height): from the body's band TOWER_BODY (under the arms, above the clutter
    round its foot) up, those in its `column` or within the band's reach, and below the
    band its legs, which spread at most TOWER_TAPER m per m from the band's own spread
    (75th percentile of the distance to the band's middle) plus TOWER_LEG_MARGIN: bushes
    and sheds round its foot, which touch it and so join its object, are not tower (the
    AHN corridor towers: 1 700 such points beside 1 200 tower points). The reach, not the
    column, bounds the legs: the column is a share of the height seen, and a flight below
    a tower's top sees a 36 m tower up to 18 m, whose legs stand 5.7 m from its axis,
    outside a column of 4.5 m (the simulated corridor's second tower). Within that spread
    the legs are still a few thin members, as the band is: a point with more than
    TOWER_LEG_CROWDING times the band's neighbours within TOWER_LEG_NEIGHBOURHOOD (its
    90th percentile, so the scan's density cancels out) lies in something that fills
    space, foliage or a footing block (07CZ2_14: a 6 m shrub under one side of a tower
    whose lattice the scan shows only from 6 m up, 380 points inside the spread;
    12AN2_20: the legs' concrete blocks 0.5-1 m high). A column without that
    band holds no body below it, where legs and bushes look alike (streamed 07CZ2_14: a
    strip holding a 6 m bush and a few of the lowest members of a known 43 m tower took
    430 bush points for its legs)."""
    lo_h, hi_h = TOWER_BODY[0] * top_h, TOWER_BODY[1] * top_h
    band = column & (h >= lo_h) & (h < hi_h)
    if band.sum() < TOWER_BAND_MIN:
        return column & (h >= lo_h)
    r = row_norm(p[:, :2] - _middle(p[band, :2]))
    reach = (np.percentile(r[band], 75) + TOWER_LEG_MARGIN
             + TOWER_TAPER * np.maximum(lo_h - h, 0.0))
    legs = np.flatnonzero((h < lo_h) & (r <= reach))
    if len(legs):
        tree = search_tree(p)  # the whole object: a shrub is crowded by its parts outside
        crowd = tree.query_ball_point(p[legs], TOWER_LEG_NEIGHBOURHOOD, return_length=True)
        own = tree.query_ball_point(p[band], TOWER_LEG_NEIGHBOURHOOD, return_length=True)
        legs = legs[crowd <= TOWER_LEG_CROWDING * np.percentile(own, 90)]
    body = (column | (r <= reach)) & (h >= lo_h)
    body[legs] = True
    return body


def _tower_feet(p: np.ndarray, h: np.ndarray, body: np.ndarray, top_h: float
                ) -> np.ndarray:
    """(F, 3) m: the tower's points (p (M, 3) m, h (M,) m above ground, `body` (M,) bool)
    below 0.3 top_h that its legs lead down to from the band: through body points in
    touching voxels of edge TOWER_FOOT_REACH / 2 (0.5 m apart always join, 1.7 m never),
    steps no longer than the foot step's own reach. A leg is one member from the body to
    the ground; a body point the legs do not lead to (the sparse fringe of a shrub, a
    footing block under a stretch of leg the scan missed) has no leg standing on the
    ground beside it (the AHN corridor: 266 ground points round two such feet, no labelled
    tower point within 2 m of the ground). Without the band (a strip holding only the
    legs) every low point is a foot."""
    low = body & (h < 0.3 * top_h)
    lower = np.flatnonzero(body & (h < TOWER_BODY[1] * top_h))
    seed = h[lower] >= TOWER_BODY[0] * top_h
    if not seed.any():
        return p[low]
    labels = voxel_components(p[lower], TOWER_FOOT_REACH / 2)
    led = np.zeros(len(p), bool)
    led[lower[np.isin(labels, labels[seed])]] = True
    return p[low & led]


def _middle(xy: np.ndarray) -> np.ndarray:
    """(2,) m: the middle of the extent (5th to 95th percentile) of (P, 2) points. A flight
    beside a tower sees its near face densely and its far face sparsely, so their mean lies
    towards the near face (the simulated corridor: 2-3 m off a 36 m tower's axis) while
    the middle of a symmetric lattice's extent is its axis."""
    n = len(xy)
    k = [int(0.05 * (n - 1)), int(np.ceil(0.95 * (n - 1)))]
    lo, hi = np.partition(xy, k, axis=0)[k]  # ~4 x faster than np.percentile
    return (lo + hi) / 2.0


def _known_columns(xy: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(P,) int: which of the towers `known` (K, 4: x, y, radius, height m) has each of the
    (P, 2) points xy (m) in its column, -1 none (the nearest when columns overlap)."""
    which = np.full(len(xy), -1)
    best = np.full(len(xy), np.inf)
    for i, k in enumerate(known):  # a few towers near a message
        d = row_norm(xy - k[:2])
        inside = (d < k[2]) & (d < best)
        which[inside], best[inside] = i, d[inside]
    return which


def _lattice(p: np.ndarray, upper: np.ndarray, column: np.ndarray) -> bool:
    """True when the upper half (`upper` (M,) bool) of an object's `column` (M,) bool, p
    (M, 3) m, is a lattice, not a solid mass: at most TOWER_MAX_SOLID of its points lie in
    voxels of LATTICE_VOXEL with SOLID_NEIGHBOURS or more of their 26 neighbours occupied
    by the object. A tower's members stand apart, while a crown is a volume of foliage.
    In a forest a few branch points pass the wire test, and a crown they touch was taken
    for a tower, remembered, and found again message after message: its upper column is
    10-65 % solid, against none of the towers of the AHN corridor tiles, whole or
    streamed, and of the simulated corridor flights."""
    up = upper & column
    if not up.any():
        return True
    _, voxel, ijk = _voxel_grid(p, column_min(p), LATTICE_VOXEL)
    solid = _occupied_neighbours(ijk) >= SOLID_NEIGHBOURS
    return float(np.mean(solid[voxel[up]])) <= TOWER_MAX_SOLID


def _carries_wires(p: np.ndarray, h: np.ndarray, top: np.ndarray, column: np.ndarray,
                   wire_xyz: np.ndarray, wire_tree: cKDTree, wire_xy_tree: cKDTree,
                   directions: _WireDirections) -> bool:
    """True when the tall object p (M, 3) m, h (M,) m above ground, whose `column` (M,) bool
    stands round the axis `top` (2,) m, carries the wires (W, 3) m (trees: wire_tree on
    xyz, wire_xy_tree on their xy; `directions` theirs on the map): wires touch it or hang
    right over its top, none passes higher over it, and they sag away from it; or so when
    only the wires of its own lines count, not those of a line crossing over at an angle
    (`_line_filter`)."""
    top_h = float(h.max())
    dist, near = wire_tree.query(p[column], distance_upper_bound=TOWER_WIRE_GAP)
    col_top = p[column, 2].max()
    # The earth wire hangs from the peak, a thin spike a scanner may miss, and the
    # conductors from arms a flight below the top may not see: wire right over the top
    # (within TOWER_PEAK, and TOWER_ARM aside) is attached to it, not passing over it.
    peak = np.asarray(wire_xy_tree.query_ball_point(top, r=TOWER_ARM), np.int64)
    peak = peak[(wire_xyz[peak, 2] >= col_top) & (wire_xyz[peak, 2] <= col_top + TOWER_PEAK)]
    touching = np.unique(np.concatenate([near[np.isfinite(dist)], peak]))
    if not len(touching):
        return False
    # It carries spans: TOWER_MIN_SPAN of wire that runs somewhere, round its top. A few
    # scattered points that passed the wire test (a slice across a roof, branches) are
    # none: streamed AHN4 had a 2 021-point piece of a building taken for a tower with
    # 2 m of such wire round it; round the towers of the AHN corridor tiles, whole and
    # streamed, and of the simulated corridor flights, 26 m and more.
    if directions.length(np.asarray(wire_xy_tree.query_ball_point(top, r=SAG_FAR),
                                    np.int64)) < TOWER_MIN_SPAN:
        return False
    if not _lattice(p, h > 0.5 * top_h, column):
        return False
    # Wire higher than that within TOWER_WIRE_GAP (horizontally) of its upper half
    # passes over it. Only the few wire points that high are searched for: a forest's
    # tall component listing the wires near each of its points cost ~9 ms a message.
    over = np.flatnonzero(wire_xyz[:, 2] > col_top + TOWER_PEAK)
    upper = p[column & (h > 0.5 * top_h), :2]
    if len(over) and len(upper):
        over = over[np.isfinite(cKDTree(upper).query(
            wire_xyz[over, :2], distance_upper_bound=TOWER_WIRE_GAP)[0])]
    else:
        over = over[:0]

    def carries(own) -> bool:
        return (not (len(over) and (own is None or own(over).any()))
                and _wires_sag_away(top, col_top, wire_xyz[touching], wire_xyz, wire_xy_tree,
                                    own))

    if carries(None):
        return True
    # Every wire says no. Those of another line crossing over it at an angle do not count:
    # a tower of a lower line beside the ground track of a higher one has that line's
    # wires passing over it, and higher than its own 15-40 m round it (a synthetic 38 m
    # tower 3-25 m from a 380 kV line's track, crossing at 30-90 degrees: vegetation).
    # Its own lines are the wires round it at its own height (not passing over), from
    # its column's edge (a tower's arms, which may be taken for wire, run across its
    # line) out to SAG_NEAR beyond. A tree or crane reaching a conductor still has that
    # line's higher ones passing over it, and its wires rising away; asked only when all
    # the wires say no, so whatever carried them before still does. A crossing line less
    # than TOWER_PEAK over the top is taken for attached, and its own (synthetic: 5.6 m
    # under it the tower is found, 4.6 m under it not).
    col_r = TOWER_RADIUS * top_h
    around = np.asarray(wire_xy_tree.query_ball_point(top, r=col_r + SAG_NEAR), np.int64)
    around = around[(row_norm(wire_xyz[around, :2] - top) > col_r)
                    & (wire_xyz[around, 2] <= col_top + TOWER_PEAK)]
    own = _line_filter(around, directions)
    return own is not None and carries(own)


def _towers(xyz: np.ndarray, hag: np.ndarray, members: np.ndarray, labels: np.ndarray,
            tall: np.ndarray, stubs: np.ndarray, wire_xyz: np.ndarray,
            known: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Which of the (M,) points `members` (indices into xyz, grouped into objects by
    `labels`) are towers, checking the `tall` objects against the wires (W, 3) or the
    towers already `known` (K, 4: x, y, radius, height m) from earlier messages, and the
    lower `stubs` (objects reaching into a known tower's column) against those.
    Returns the (M,) bool, the feet (F, 3) of each tower, and the towers (T, 4) found."""
    is_tower = np.zeros(len(members), bool)
    feet: list[np.ndarray] = []
    found: list[tuple[float, float, float, float]] = []
    if (len(wire_xyz) == 0 and len(known) == 0) or len(tall) + len(stubs) == 0:
        return is_tower, feet, np.zeros((0, 4))
    wire_tree = cKDTree(wire_xyz) if len(wire_xyz) else None
    wire_xy_tree = cKDTree(wire_xyz[:, :2]) if len(wire_xyz) else None
    directions = _WireDirections(wire_xyz)
    judged = np.concatenate([tall, stubs])
    # the judged objects' members, grouped by one stable sort (in index order within each),
    # not one scan of every member per object: a corridor strip has tens of tall trees
    mine = np.flatnonzero(np.isin(labels, judged))
    mine = mine[np.argsort(labels[mine], kind="stable")]
    first = np.searchsorted(labels[mine], judged, side="left")
    last = np.searchsorted(labels[mine], judged, side="right")
    for lab, lo, hi in zip(judged, first, last):
        local = mine[lo:hi]
        p, h = xyz[members[local]], hag[members[local]]
        top_h = float(h.max())
        # A tower carries wires: they end at its arms, at or below its top (a tree under
        # the line stays below the wires next to it). Trees touching the tower join its
        # component, so only the column around its axis is tower: the middle of its upper
        # half, arms and all (`_middle`: a flight beside a tower sees its near face densely).
        top = _middle(p[h > 0.5 * top_h, :2])
        stub = lab in stubs
        seen = _known_columns(top[None], known)[0] if len(known) and not stub else -1
        if stub:
            seen, top = _known_tower_of_stub(p, h, known)
            if seen < 0:
                continue
        column = row_norm(p[:, :2] - top) < TOWER_RADIUS * top_h
        if not column.any():
            continue  # no mast at the top's middle: a ring of tall things
        carries = (not stub and wire_tree is not None
                   and _carries_wires(p, h, top, column, wire_xyz, wire_tree, wire_xy_tree,
                                      directions))
        if seen < 0 and not carries:
            continue
        tower_h = top_h
        if seen >= 0:
            # Seen in an earlier strip: this strip may hold only part of it (the legs).
            # Its column and height are the tower's, not the part's.
            column |= row_norm(p[:, :2] - known[seen, :2]) < known[seen, 2]
            tower_h = max(top_h, float(known[seen, 3]))
        body = _tower_body(p, h, column, tower_h)
        is_tower[local[body]] = True
        feet.append(_tower_feet(p, h, body, tower_h))
        if carries:
            # Every view that carries wires is remembered, also of a known tower: the first
            # strip to see the simulated corridor's second tower held its front only and
            # put its axis 2.2 m off; the strips leaving it hold its back, whose band's
            # middle lies 5 m from that first view's axis.
            found.append((float(top[0]), float(top[1]), TOWER_RADIUS * tower_h, tower_h))
    return is_tower, feet, _widest_towers(found)


def _known_tower_of_stub(p: np.ndarray, h: np.ndarray, known: np.ndarray
                         ) -> tuple[int, np.ndarray]:
    """Which of the towers `known` (K, 4: x, y, radius, height m) the object p (M, 3) m, h
    (M,) m above ground, lower than a tower, is the lower part of (-1: none), and the
    middle (2,) m of that tower's band TOWER_BODY in it (zeros for none): the first of the
    towers in whose column it has points (in their order) of whose band it holds
    TOWER_BAND_MIN points or more, the band's middle (`_middle`) standing in its column.
    A strip leaving the simulated corridor's towers holds lattices 3-15 m high that were
    18-28 m towers a second earlier; without the band, a tower's legs and the bushes round
    them look alike."""
    inside = _known_columns(p[:, :2], known)
    for k in np.unique(inside[inside >= 0]):
        band = (h >= TOWER_BODY[0] * known[k, 3]) & (h < TOWER_BODY[1] * known[k, 3])
        if band.sum() < TOWER_BAND_MIN:
            continue
        middle = _middle(p[band, :2])
        if row_norm(middle[None] - known[k, :2])[0] < known[k, 2]:
            return int(k), middle
    return -1, np.zeros(2)


def _widest_towers(found: list[tuple[float, float, float, float]]) -> np.ndarray:
    """(T, 4) x, y, radius, height (m): the towers `found` (the same, one tuple each) less
    those whose axis stands in the column of a wider one kept: pieces of one tower (arms
    cut off by the wires) are one tower, and the widest stands."""
    towers: list[tuple[float, float, float, float]] = []
    for t in sorted(found, key=lambda t: -t[2]):
        if all(np.hypot(t[0] - k[0], t[1] - k[1]) >= k[2] for k in towers):
            towers.append(t)
    return np.array(towers).reshape(-1, 4)


def classify_obstacles(xyz: np.ndarray, ground: np.ndarray, height_above_ground: np.ndarray, *,
                       cfg: ObstaclesConfig, rng: np.random.Generator | None = None,
                       known_towers: np.ndarray | None = None,
                       known_wires: np.ndarray | None = None,
                       known_buildings: np.ndarray | None = None,
                       context: np.ndarray | None = None) -> ObstacleClasses:
    """Classes of every point of (N, 3) float64 xyz (m) given the ground mask (N,) bool and
    the height above ground (N,) float32 m (NaN: unknown, taken as 0). known_towers: (K, 4)
    x, y, radius, height (m) of towers recognised in earlier messages
    (ObstacleClasses.towers);
    known_wires: (W, 4) wire points of earlier messages (ObstacleClasses.wires; (W, 3): all
    taken as tested), of which only those supported (`_supported_wires`) lead on;
    known_buildings: (B, 4) their building points (ObstacleClasses.buildings);
    context: (C, 3) m, points of earlier messages beyond a thin strip's edge, neighbours in
    the shape features only (`shape_context`). rng draws the buildings' RANSAC samples
    (None: a generator seeded RANSAC_SEED, so that a cloud's classes are the same in every
    run; the detector passes its own, seeded from its config).

    The steps are those of the module's docstring, each a function below: every point off
    the ground starts as vegetation by its height and keeps that class unless a step
    gives it another."""
    rng = rng if rng is not None else np.random.default_rng(RANSAC_SEED)
    n = len(xyz)
    classes = np.full(n, GROUND, np.uint8)
    object_id = np.full(n, -1, np.int32)
    if n == 0:
        return ObstacleClasses(classes, object_id, ())
    hag = np.nan_to_num(np.asarray(height_above_ground, np.float64), nan=0.0)
    off_ground = np.flatnonzero(~ground)
    classes[off_ground] = vegetation_class(hag[off_ground])
    # 1. noise
    off_ground, lone_high = _mark_noise(xyz, hag, off_ground, cfg, classes)
    cand = off_ground[hag[off_ground] >= cfg.min_height]  # the candidates: shapes sought
    known_wires = _supported_wires(known_wires)
    known_buildings = (np.zeros((0, 4)) if known_buildings is None
                       else np.asarray(known_buildings, float).reshape(-1, 4))
    if len(cand) < 3:
        return ObstacleClasses(classes, object_id, (), candidates=xyz[cand])
    # the candidates' neighbourhood shapes: linearity, planarity, main axis, roughness
    shape = local_shape(xyz[cand], cfg.feature_radius, context=context)
    # 2. wires; a strip across a roof an earlier message found is level and linear too
    is_wire = _wires(xyz, cand, hag, shape, cfg, known_wires)
    if is_wire.any() and (known_buildings[:, 3] > 0).any():
        is_wire[is_wire] = ~_on_known_roofs(xyz[cand[is_wire]], known_buildings)
    tested = is_wire.copy()  # passed the wire test itself (not followed through a crown)
    classes[cand[is_wire]] = WIRE
    # 3. objects of the rest; towers among the tall ones, by the wires of this message
    # and of earlier ones (a strip may catch a tower but not the wires it carries)
    groups = _group_objects(xyz, cand, hag, is_wire, cfg, object_id)
    wire_xyz = np.concatenate([xyz[cand[is_wire]], known_wires])
    tower, tower_feet, towers = _tower_objects(xyz, hag, cand, groups, wire_xyz, known_towers,
                                               cfg)
    classes[cand[tower]] = TOWER
    # 4. buildings: large planar patches (and what clings to them), and the feet of walls
    is_building, roofs = _buildings(xyz, cand, shape, ~is_wire & ~tower, cfg, rng,
                                    known_buildings, hag[cand])
    classes[cand[is_building]] = BUILDING
    _wall_feet(xyz, off_ground[hag[off_ground] < cfg.min_height],
               cand[roofs & (hag[cand] < cfg.min_height + WALL_FOOT_BAND)], classes)
    # 5. poles and structures; wires go on through crowns and clutter (not into towers or
    # roofs); the ground under a tower's legs
    _mark_poles_and_structures(cand, shape, groups, tower, is_building, classes)
    if is_wire.any() or len(known_wires):
        _extend_wires(xyz, cand, hag, shape, cfg, is_wire, is_building, tower, known_wires)
        classes[cand[is_wire]] = WIRE
    _mark_tower_feet(xyz, tower_feet, classes)
    # what the next message is told: the wires and buildings, thinned
    wires = _memory_rows(xyz[cand[is_wire]], tested[is_wire], WIRE_MEMORY_VOXEL)
    buildings = _memory_rows(xyz[cand[is_building]], roofs[is_building],
                             BUILDING_MEMORY_VOXEL)
    # objects and their boxes: the buildings', wires' and towers' own; a thin wire's lone
    # echoes join their wire's; what the others left of an object is grouped again
    next_id = _number_class_objects(
        xyz, cand, ((is_building, OBJECT_LINK), (is_wire, OBJECT_LINK), (tower, TOWER_LINK)),
        groups.next_id, object_id)
    taken = is_building | is_wire | tower
    if is_wire.any():
        echoes = _wire_echoes(xyz, _echo_candidates(hag, cand, groups, lone_high, classes, cfg),
                              cand[is_wire], shape.axis[is_wire], classes, object_id)
        taken |= np.isin(cand, echoes)  # (in their wire's object, not regrouped)
    _regroup_leftovers(xyz[cand[groups.rest]], groups.labels, groups.kept, taken[groups.rest],
                       object_id, cand[groups.rest], next_id, cfg)
    objects = _objects(xyz, hag, classes, object_id)
    return ObstacleClasses(classes, object_id, tuple(objects), towers, wires, buildings,
                           xyz[cand])


def _mark_noise(xyz: np.ndarray, hag: np.ndarray, off_ground: np.ndarray,
                cfg: ObstaclesConfig, classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Class NOISE for the non-ground points `off_ground` (indices into xyz (N, 3) m; hag
    (N,) m above ground) with fewer than cfg.noise_min_neighbours others within
    cfg.noise_radius m (`_isolated`) or more than BELOW_GROUND_NOISE m below the ground;
    classes (N,) is updated in place. Returns the indices of the other points of
    `off_ground`, and those of the isolated ones more than cfg.wire_min_clearance m up,
    which may yet be a thin wire's lone echoes (`_wire_echoes`)."""
    if len(off_ground) == 0:
        return off_ground, off_ground
    isolated = _isolated(xyz[off_ground], cfg.noise_radius, cfg.noise_min_neighbours)
    noise = isolated | (hag[off_ground] < -BELOW_GROUND_NOISE)
    classes[off_ground[noise]] = NOISE
    lone_high = off_ground[isolated & (hag[off_ground] > cfg.wire_min_clearance)]
    return off_ground[~noise], lone_high


@dataclass(frozen=True)
class _Objects:
    """The candidates other than wire, grouped into objects (`_group_objects`): rest (R,)
    their indices among the candidates and labels (R,) their object 0..L-1; per object,
    kept (L,) bool: of cfg.min_points or more (an object; the others belong to none),
    extent (L,) m: its box's horizontal diagonal, height (L,) m: its highest point above
    ground; next_id: the first object id not taken by them."""

    rest: np.ndarray
    labels: np.ndarray
    kept: np.ndarray
    extent: np.ndarray
    height: np.ndarray
    next_id: int


def _group_objects(xyz: np.ndarray, cand: np.ndarray, hag: np.ndarray, is_wire: np.ndarray,
                   cfg: ObstaclesConfig, object_id: np.ndarray) -> _Objects:
    """The candidates `cand` (C,) (indices into xyz (N, 3) m; hag (N,) m above ground) other
    than wire (is_wire (C,) bool) grouped into objects: connected components of the voxels
    of edge cfg.cluster_distance m. object_id (N,) is set, in place, to their label for the
    points of the objects kept."""
    rest = np.flatnonzero(~is_wire)
    labels = voxel_components(xyz[cand[rest]], cfg.cluster_distance)
    count, extent, height = _label_stats(labels, xyz[cand[rest]], hag[cand[rest]])
    kept = count >= cfg.min_points
    object_id[cand[rest[kept[labels]]]] = labels[kept[labels]]
    next_id = int(labels.max()) + 1 if len(labels) else 0
    return _Objects(rest, labels, kept, extent, height, next_id)


def _tower_objects(xyz: np.ndarray, hag: np.ndarray, cand: np.ndarray, groups: _Objects,
                   wire_xyz: np.ndarray, known_towers: np.ndarray | None,
                   cfg: ObstaclesConfig) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Which objects `groups` of the candidates `cand` (C,) (indices into xyz (N, 3) m; hag
    (N,) m above ground) are towers (`_towers`): those taller than cfg.tower_min_height
    that carry the wires wire_xyz (W, 3) m or stand where one of known_towers (K, 4: x, y,
    radius, height m; None: none) stood, and the lower ones that are a known tower's lower
    part (`_tower_stubs`). Returns the tower points (C,) bool over the candidates, the feet
    (F, 3) m of each tower (`_tower_feet`) and the towers (T, 4) found."""
    known = (np.zeros((0, 4)) if known_towers is None
             else np.asarray(known_towers, float).reshape(-1, 4))
    tall = groups.kept & (groups.height > cfg.tower_min_height)
    stubs = _tower_stubs(xyz, cand, groups, tall, known)
    is_tower, feet, towers = _towers(
        xyz, hag, cand[groups.rest], groups.labels, np.flatnonzero(tall), np.flatnonzero(stubs),
        wire_xyz, known)
    tower = np.zeros(len(cand), bool)
    tower[groups.rest[is_tower]] = True
    return tower, feet, towers


def _tower_stubs(xyz: np.ndarray, cand: np.ndarray, groups: _Objects, tall: np.ndarray,
                 known: np.ndarray) -> np.ndarray:
    """(L,) bool: the objects `groups` (of the candidates `cand`, indices into xyz (N, 3) m)
    kept but not `tall` (L,) bool that reach the lowest band TOWER_BODY of the towers
    `known` (K, 4: x, y, radius, height m) and have a point in one's column. Only those
    objects' points are searched: all points of the corridor flight's messages cost
    ~2 ms."""
    low = groups.kept & ~tall
    stubs = np.zeros(len(groups.kept), bool)
    if len(known):
        low &= groups.height >= TOWER_BODY[0] * known[:, 3].min()
        look = groups.rest[low[groups.labels]]
        stubs[groups.labels[low[groups.labels]][_known_columns(xyz[cand[look], :2], known)
                                                >= 0]] = True
    return stubs


def _mark_poles_and_structures(cand: np.ndarray, shape: LocalShape, groups: _Objects,
                               tower: np.ndarray, is_building: np.ndarray,
                               classes: np.ndarray) -> None:
    """Class UNCLASSIFIED for the points of the objects `groups` kept that are slender (a
    box's horizontal diagonal under POLE_MAX_EXTENT m, more than POLE_MIN_HEIGHT m high:
    poles) or built of beams (`_structures`: cranes, masts), those points that are neither
    tower nor building (tower, is_building (C,) bool over the candidates `cand`, indices
    into classes (N,), updated in place; shape: the candidates' `local_shape`)."""
    rest, labels = groups.rest, groups.labels
    slender = (groups.extent < POLE_MAX_EXTENT) & (groups.height > POLE_MIN_HEIGHT)
    beams = _structures(labels, shape, rest, groups.height, groups.extent)
    pole = (groups.kept & (slender | beams))[labels] & ~tower[rest]
    classes[cand[rest[pole & ~is_building[rest]]]] = UNCLASSIFIED


def _extend_wires(xyz: np.ndarray, cand: np.ndarray, hag: np.ndarray, shape: LocalShape,
                  cfg: ObstaclesConfig, is_wire: np.ndarray, is_building: np.ndarray,
                  tower: np.ndarray, known_wires: np.ndarray) -> None:
    """Grow is_wire (C,) bool over the candidates `cand` (indices into xyz (N, 3) m; hag
    (N,) m above ground; shape their `local_shape`) in place: the wires of this message,
    and those of earlier ones known_wires (K, 3) m (`_known_wire_seeds`), followed along
    their own axis (`_follow_wires`) through the candidates more than
    cfg.wire_min_clearance m up that are neither building nor tower (is_building, tower
    (C,) bool)."""
    followable = (hag[cand] > cfg.wire_min_clearance) & ~is_building & ~tower
    seeds, seed_axis = _known_wire_seeds(known_wires, xyz[cand[followable]],
                                         xyz[cand[is_wire]], cfg)
    _follow_wires(xyz[cand], followable, shape.axis, is_wire, seeds, seed_axis)


def _mark_tower_feet(xyz: np.ndarray, tower_feet: list[np.ndarray],
                     classes: np.ndarray) -> None:
    """Class TOWER for the ground points (of xyz (N, 3) m, classes (N,) updated in place)
    within TOWER_FOOT_REACH m of a tower's feet (tower_feet: (F, 3) m each,
    `_tower_feet`): the ground right under its legs, not its whole footprint. A tower's
    lowest points lie within the ground filter's band, but a UAV must never take its legs
    for ground."""
    feet = [f for f in tower_feet if len(f)]
    if not feet:
        return
    ground_ids = np.flatnonzero(classes == GROUND)
    dist, _ = tree_query(search_tree(np.concatenate(feet)), xyz[ground_ids],
                         distance_upper_bound=TOWER_FOOT_REACH,
                         workers=_workers(len(ground_ids)))
    classes[ground_ids[np.isfinite(dist)]] = TOWER


def _memory_rows(pts: np.ndarray, flag: np.ndarray, edge: float) -> np.ndarray:
    """(V, 4) rows a message hands on (ObstacleClasses.wires, .buildings): the points pts
    (P, 3) m thinned to the centroid (m) of each occupied voxel of `edge` m (counted from
    their lowest corner), and 1 where a point of the voxel is flagged (flag (P,) bool),
    else 0."""
    if len(pts) == 0:
        return np.zeros((0, 4))
    centroids, voxel = _voxel_centroids(pts, column_min(pts), edge)
    return np.column_stack([centroids, np.bincount(voxel, flag, len(centroids)) > 0])


def _number_class_objects(xyz: np.ndarray, cand: np.ndarray,
                          parts: tuple[tuple[np.ndarray, float], ...], next_id: int,
                          object_id: np.ndarray) -> int:
    """Objects of their own for the points of each class in `parts`, (mask (C,) bool over
    the candidates `cand`, indices into xyz (N, 3) m; link m) in turn: the connected
    components of their voxels of edge `link`, numbered from next_id on. object_id (N,) is
    updated in place; returns the first id not taken."""
    for mask, link in parts:
        ids = cand[mask]
        if len(ids):
            runs = voxel_components(xyz[ids], link)
            object_id[ids] = next_id + runs
            next_id += int(runs.max()) + 1
    return next_id


def _echo_candidates(hag: np.ndarray, cand: np.ndarray, groups: _Objects,
                     lone_high: np.ndarray, classes: np.ndarray,
                     cfg: ObstaclesConfig) -> np.ndarray:
    """Indices (into hag (N,) m above ground and classes (N,)) of the points that may be a
    thin wire's echoes (`_wire_echoes`): the isolated points `lone_high` (indices) more
    than cfg.wire_min_clearance m up, then the points of the candidates' pieces too small
    to be objects (`groups`) that high that are still vegetation by height."""
    small = cand[groups.rest[~groups.kept[groups.labels]]]
    small = small[(hag[small] > cfg.wire_min_clearance)
                  & (vegetation_class(hag[small]) == classes[small])]
    return np.concatenate([lone_high, small])


def _wire_echoes(xyz: np.ndarray, lone: np.ndarray, wire: np.ndarray, axis: np.ndarray,
                 classes: np.ndarray, object_id: np.ndarray) -> np.ndarray:
    """Class WIRE, and the object of the wire point that vouches for it, for those of the
    isolated points and too-small pieces `lone` (indices into xyz (N, 3) m) that lie on
    the line of one of their 8 nearest wire points `wire` (indices; axis (W, 3) their
    main axes, unit) within WIRE_ECHO_REACH: within WIRE_ECHO_TUBE + WIRE_ECHO_SAG x the
    distance along that axis. classes and object_id (N,) are updated in place; returns
    the indices made wire."""
    if len(lone) == 0:
        return lone
    k = min(8, len(wire))
    dist, idx = tree_query(search_tree(xyz[wire]), xyz[lone], k=k,
                           distance_upper_bound=WIRE_ECHO_REACH)
    dist, idx = dist.reshape(len(lone), k), idx.reshape(len(lone), k)
    found = np.isfinite(dist)
    nearest = np.where(found, idx, 0)
    a = axis[nearest]  # (L, k, 3)
    offset = xyz[lone][:, None, :] - xyz[wire[nearest]]
    along = np.einsum("lkj,lkj->lk", offset, a)
    off = np.linalg.norm(offset - along[..., None] * a, axis=-1)
    on_line = (found & np.isfinite(off) & (np.linalg.norm(a, axis=-1) > 0.5)
               & (off <= WIRE_ECHO_TUBE + WIRE_ECHO_SAG * np.abs(along)))
    hit = on_line.any(axis=1)
    if hit.any():
        first = np.argmax(on_line[hit], axis=1)
        classes[lone[hit]] = WIRE
        object_id[lone[hit]] = object_id[wire[nearest[hit, first]]]
    return lone[hit]


def _structures(labels: np.ndarray, shape: LocalShape, rest: np.ndarray,
                height: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """(L,) bool: which of the objects labelled 0..L-1 (labels (R,) of the candidates
    `rest` (R,) indices into `shape`'s points; height (L,) m, the object's top above
    ground; extent (L,) m, its box's horizontal diagonal) are built of beams, not grown:
    taller than STRUCTURE_MIN_HEIGHT, wider than STRUCTURE_MIN_EXTENT, of
    STRUCTURE_MIN_POINTS points or more, with STRUCTURE_BEAMS of its points on steep lines
    (linearity over STRUCTURE_LINEARITY, main axis over STRUCTURE_STEEP from horizontal:
    jibs, masts, lattice members) and smooth (mean roughness under STRUCTURE_ROUGHNESS).

    Cranes otherwise stand among the trees as high vegetation. The corridor files'
    cranes' objects hold 11-29 % of points on steep lines, roughness 0.14-0.24 m, and are
    8.9-27.6 m wide; their trees and AHN4's 1-7 %, 0.28-0.42 m. Young trees of the
    simulated flights, a trunk under a small crown, pass the beams and the roughness but
    are 3.4-5.5 m wide. Pieces of towers not found as such (4-17 m wide) are structures
    too."""
    n = np.bincount(labels, minlength=len(height))
    steep = np.abs(shape.axis[rest, 2]) > np.sin(np.radians(STRUCTURE_STEEP))
    beams = (shape.linearity[rest] > STRUCTURE_LINEARITY) & steep
    share = np.bincount(labels, beams, len(height)) / np.maximum(n, 1)
    rough = np.bincount(labels, shape.roughness[rest], len(height)) / np.maximum(n, 1)
    return ((height > STRUCTURE_MIN_HEIGHT) & (extent > STRUCTURE_MIN_EXTENT)
            & (n >= STRUCTURE_MIN_POINTS) & (share >= STRUCTURE_BEAMS)
            & (rough < STRUCTURE_ROUGHNESS))


def _wall_feet(xyz: np.ndarray, low: np.ndarray, walls: np.ndarray,
               classes: np.ndarray) -> None:
    """Class BUILDING for the points `low` (indices of non-ground points below
    `obstacles.min_height`) that stand under a wall: within WALL_FOOT_REACH on the map of
    the points `walls` (indices: the lowest band of the buildings' own planar or curved
    patches, not what clings to them). Without this those feet are low vegetation, the
    commonest wrong class after the ground's band. The band reaches WALL_FOOT_BAND 3 m
    above `min_height`: a wall's patch often starts a metre or two up (its lowest part,
    rough near the ground, clings to it). Not the band of everything labelled building:
    on AHN4 that is mostly fences and sheds beside the walls. classes (N,) is updated in
    place."""
    if len(low) == 0 or len(walls) == 0:
        return
    near = np.flatnonzero(all_columns((xyz[low, :2] >= column_min(xyz[walls, :2]) - 1.0)
                                      & (xyz[low, :2] <= column_max(xyz[walls, :2]) + 1.0)))
    if len(near) == 0:
        return
    dist, _ = tree_query(search_tree(xyz[walls, :2]), xyz[low[near], :2],
                         distance_upper_bound=WALL_FOOT_REACH, workers=_workers(len(near)))
    classes[low[near[np.isfinite(dist)]]] = BUILDING


def _regroup_leftovers(xyz: np.ndarray, labels: np.ndarray, kept: np.ndarray,
                       taken: np.ndarray, object_id: np.ndarray, where: np.ndarray,
                       next_id: int, cfg: ObstaclesConfig) -> None:
    """Make objects again of what is left of the objects that lost points to a tower, a
    building or a wire (which are objects of their own): a tree touching a tower's leg
    was one object with it, and its box, labelled by the more numerous tree points, held
    the tower (07CZ2_14: a 1 362-point tower in a 6 982-point "high vegetation" box, and no
    tower box). What is left is grouped anew, as the first grouping did.

    xyz (R, 3) m, the points grouped first, with their object labels (R,) and which
    labels were objects `kept` (L,) bool; taken (R,) bool: now in an object of their own.
    object_id (N,) is updated at `where` (R,) indices, new ids from next_id on."""
    lost = np.zeros(len(kept), bool)
    lost[labels[taken]] = True
    left = np.flatnonzero(lost[labels] & kept[labels] & ~taken)
    if len(left) == 0:
        return
    pieces = voxel_components(xyz[left], cfg.cluster_distance)
    big = np.bincount(pieces) >= cfg.min_points
    object_id[where[left]] = np.where(big[pieces], next_id + pieces, -1)


def _objects(xyz: np.ndarray, hag: np.ndarray, classes: np.ndarray,
             object_id: np.ndarray) -> list[ObstacleObject]:
    """Boxes of the objects, vectorised over points (one pass per statistic)."""
    sel = np.flatnonzero(object_id >= 0)
    if len(sel) == 0:
        return []
    # (a table, not np.unique's sort: a forest strip's 46 000 points in 10 objects took
    # 8 ms to sort, many equal keys being quicksort's slow case)
    ids, inv = unique_ints(object_id[sel].astype(np.int64))
    counts = np.bincount(inv)
    k = len(ids)
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    for a in range(3):
        np.minimum.at(lo[:, a], inv, xyz[sel, a])
        np.maximum.at(hi[:, a], inv, xyz[sel, a])
    hmax = np.full(k, -np.inf)
    hmin = np.full(k, np.inf)
    np.maximum.at(hmax, inv, hag[sel])
    np.minimum.at(hmin, inv, hag[sel])
    # class of an object: its most common point class
    cls_count = np.bincount(inv * 256 + classes[sel], minlength=k * 256).reshape(k, 256)
    cls = cls_count.argmax(axis=1)
    return [ObstacleObject(int(ids[i]), int(cls[i]), int(counts[i]), lo[i], hi[i],
                           float(hmax[i]), float(hmin[i]))
            for i in range(k)]


def clearance_grid(xyz: np.ndarray, classes: np.ndarray, height_above_ground: np.ndarray, *,
                   centre_xy: np.ndarray, cfg: ClearanceConfig
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Occupancy grid around centre_xy (2,) m: per cell the tallest obstacle above ground
    scaled to 0..100 (cfg.max_height -> 100); -1 where no point fell; 0 where only
    ground/low points. xyz (N, 3) m, classes (N,) ASPRS codes, height_above_ground (N,) m
    (NaN taken as 0).

    Returns (cells (rows, cols) int8, row = y index; origin (2,) lower-left corner, m;
    resolution m)."""
    res = cfg.resolution
    side = max(1, int(round(cfg.size / res)))
    # centred on the grid's own span: `size` rounded to whole cells (100 m of 30 m cells
    # made 90 m, placed as if 100 m, the vehicle 5 m off its middle)
    origin = np.floor((np.asarray(centre_xy, float) - side * res / 2) / res) * res
    cells = np.full((side, side), -1, np.int8)
    # one column at a time (no (N, 2) temporaries); a NaN x or y compares false: outside
    col, row = ((xyz[:, a] - origin[a]) / res for a in (0, 1))
    inside = (col >= 0) & (col < side) & (row >= 0) & (row < side) & np.isfinite(xyz[:, 2])
    if not inside.any():
        return cells, origin, res
    flat = row[inside].astype(np.int64) * side + col[inside].astype(np.int64)  # >= 0: floor
    cls = classes[inside]
    obstacle = (cls != GROUND) & (cls != NOISE)
    h = np.where(obstacle, np.nan_to_num(height_above_ground[inside].astype(float), nan=0.0), 0.0)
    top = np.full(side * side, -1.0)
    np.maximum.at(top, flat, np.maximum(h, 0.0))
    seen = top >= 0
    value = np.full(side * side, -1, np.int8)
    value[seen] = np.clip(np.round(100.0 * top[seen] / cfg.max_height), 0, 100).astype(np.int8)
    return value.reshape(side, side), origin, res
