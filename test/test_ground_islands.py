"""Raised islands and pits in the hybrid ground filter (_islands_and_pits): on dense scans
a roof that a strip caught in its corner, which no window of the opening can cut off,
leaves the ground; stray low points do not take the ground with them, and leave it
themselves when ground surrounds them; lone low echoes beyond a strip's edge leave it;
terraces and a quarry stay."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.core.ground import HybridSettings, morphological_ground

DENSITY = 8.0  # points per m^2, a UAV or AHN scan


def _flat(rng: np.random.Generator, lo: tuple[float, float], hi: tuple[float, float]
          ) -> np.ndarray:
    """(N, 3) flat ground at z = 0 (+-0.03 m) over the box lo..hi (m)."""
    n = int((hi[0] - lo[0]) * (hi[1] - lo[1]) * DENSITY)
    xy = rng.uniform(lo, hi, (n, 2))
    return np.column_stack([xy, rng.normal(0.0, 0.03, n)])


def _roof_in_the_corner(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) centred points of a 30 x 80 m strip whose lower right corner is a flat roof,
    25 x 20 m and 8 m up, with its 4 m shadow beside it; (N,) bool roof."""
    rng = np.random.default_rng(seed)
    pts = _flat(rng, (0.0, 0.0), (30.0, 80.0))
    roof = (pts[:, 0] > 5.0) & (pts[:, 1] < 20.0)
    shadow = (pts[:, 0] > 1.0) & (pts[:, 1] < 20.0) & ~roof
    pts[roof, 2] += 8.0
    pts, roof = pts[~shadow], roof[~shadow]
    return pts - pts.mean(axis=0), roof


def test_a_roof_in_a_strips_corner_is_no_ground():
    pts, roof = _roof_in_the_corner()
    ground, height = morphological_ground(pts, HybridSettings())
    assert not ground[roof].any()
    assert ground[~roof].mean() > 0.99
    # Its height above ground is the building's, not 0 (the clearance grid reads it).
    assert np.median(pts[roof, 2] - height[roof]) > 7.0
    # Without the test the roof is ground: the opening's windows cut at the strip's edges
    # never hold ground on every side of it.
    plain, _ = morphological_ground(pts, HybridSettings(island_rise=0))
    assert plain[roof].mean() > 0.9


def _strip_with_low_points(where: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) centred points of a flat 30 x 40 m strip with two low points 4-4.6 m down
    that shield each other from the blunder test; (N,) bool low. where: "edge" (two
    cells apart on the strip's edge, an empty row between them and the ground) or
    "inside" (neighbouring cells in the middle)."""
    rng = np.random.default_rng(1)
    if where == "edge":
        pts = _flat(rng, (0.0, 2.0), (30.0, 42.0))
        low = np.array([[10.2, 0.3, -4.0], [12.4, 0.4, -4.6]])
    else:
        pts = _flat(rng, (0.0, 0.0), (30.0, 40.0))
        low = np.array([[15.3, 20.5, -4.0], [16.4, 20.5, -4.3]])
    pts = np.concatenate([pts, low])
    is_low = np.zeros(len(pts), bool)
    is_low[-2:] = True
    return pts - pts.mean(axis=0), is_low


def test_stray_low_points_do_not_raise_the_ground_into_an_island():
    for where, unguarded in (("edge", {"island_min_cells": 1, "island_pit_share": 2.0}),
                             ("inside", {"island_pit_share": 2.0})):
        pts, low = _strip_with_low_points(where)
        ground, _ = morphological_ground(pts, HybridSettings())
        assert ground[~low].mean() > 0.99, where
        if where == "inside":  # a pit: ground all round it
            assert not ground[low].any()
        # Counted as lower ground, they would make the whole strip one raised island.
        bare, _ = morphological_ground(pts, HybridSettings(**unguarded))
        assert bare[~low].mean() < 0.1, where


def test_terraces_and_a_quarry_stay_ground():
    rng = np.random.default_rng(2)
    # Three terraces stepping up 3 m each at vertical walls: each has the next one above.
    pts = _flat(rng, (0.0, 0.0), (45.0, 60.0))
    pts[:, 2] += 3.0 * np.floor(pts[:, 0] / 15.0)
    ground, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings())
    assert ground.mean() > 0.99
    # A quarry 20 x 20 m and 5 m deep in 80 x 80 m of land: the land is raised above the
    # floor all round, but it is wider than any roof (island_extent).
    pts = _flat(rng, (0.0, 0.0), (80.0, 80.0))
    floor = (np.abs(pts[:, 0] - 40.0) < 10.0) & (np.abs(pts[:, 1] - 40.0) < 10.0)
    pts[floor, 2] -= 5.0
    ground, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings())
    assert ground[~floor].mean() > 0.99
    assert ground[floor].mean() > 0.95


def test_no_island_test_on_sparse_scans():
    rng = np.random.default_rng(3)
    pts, roof = _roof_in_the_corner()
    keep = rng.random(len(pts)) < 0.5 / DENSITY  # 0.5 points per m^2
    on, _ = morphological_ground(pts[keep], HybridSettings())
    off, _ = morphological_ground(pts[keep], HybridSettings(island_rise=0))
    assert np.array_equal(on, off)
    # So the corner roof stays ground there (a known limit): most 1 m cells are empty,
    # and pieces of ground do not connect.
    assert on[roof[keep]].mean() > 0.5


def test_lone_low_echoes_beyond_a_strips_edge_leave_the_ground():
    """A low noise echo at a strip's far edge lies beyond the last scan line, with nothing
    around it for the low-blunder test to judge it on: it is a blunder when it lies more
    than low_outlier plus lone_slope times the distance below the nearest cells; a lone
    point that follows the terrain's own fall stays."""
    rng = np.random.default_rng(4)
    pts = _flat(rng, (0.0, 0.0), (30.0, 40.0))
    pts[:, 2] += 0.2 * pts[:, 1]  # the land falls towards the edge at y = 0
    echoes = np.array([[2.3, -5.2, -6.0], [23.6, -7.4, -9.5], [28.1, -4.6, -5.6],
                       [24.9, -6.1, -8.8]])  # the last three a few metres apart
    terrain = np.array([[13.2, -6.1, -1.3]])  # 6 m out, as low as the slope goes on
    pts = np.concatenate([pts, echoes, terrain])
    pts -= pts.mean(axis=0)
    is_echo = np.zeros(len(pts), bool)
    is_echo[-5:-1] = True
    ground, height = morphological_ground(pts, HybridSettings())
    assert not ground[is_echo].any()
    assert ground[-1]
    assert ground[~is_echo].mean() > 0.99
    # The surface is not dragged down towards them: the echoes are metres below it.
    assert (pts[is_echo, 2] - height[is_echo] < -3.0).all()
    # Without the test they are ground (nothing within the blunder or pit windows).
    plain, _ = morphological_ground(pts, HybridSettings(lone_reach=0))
    assert plain[is_echo].all()
    # Judged one cell at a time, the three close together shield each other.
    single, _ = morphological_ground(pts, HybridSettings(lone_cells=1))
    assert single[is_echo][1:].all() and not single[is_echo][0]
    # A real ground point in an echo's cell (5 cm from it, on the terrain) stays ground:
    # only the points near the cell's lowest leave with it.
    beside = np.concatenate([pts, pts[-5:-4] + [0.05, 0.05, 0.0]])
    beside[-1, 2] = pts[-1, 2] + 0.2 * (beside[-1, 1] - pts[-1, 1])  # as the land falls
    ground, _ = morphological_ground(beside, HybridSettings())
    assert not ground[-6] and ground[-1]


def test_a_steep_gable_roof_in_a_strips_corner_and_its_walls_are_no_ground():
    """The roof in the corner, pitched at 45 degrees (eaves 6 m up, ridge 16 m): within
    island_reach its ridge stands over its own eaves, which is no higher ground beside it,
    and its walls, in the band of the surface across the roof, leave with it (simulated
    urban flight, seed 2: 2 565 points of a roof 10-13 m up taken for ground in one
    message; wall points 1-3 m up in others)."""
    rng = np.random.default_rng(5)
    pts = _flat(rng, (0.0, 0.0), (30.0, 80.0))
    roof = (pts[:, 0] > 5.0) & (pts[:, 1] < 20.0)
    shadow = (pts[:, 0] > 1.0) & (pts[:, 1] < 20.0) & ~roof
    pts[roof, 2] += 6.0 + 10.0 - np.abs(pts[roof, 0] - 15.0)  # ridge along y at x = 15
    u, v = rng.uniform(0.0, 1.0, (2, 600))
    walls = np.concatenate([  # the west wall and the north gable end, 0.2 m off the roof
        np.column_stack([np.full(300, 5.0), 20.0 * u[:300], 6.0 * v[:300]]),
        np.column_stack([5.0 + 20.0 * u[300:], np.full(300, 20.0), 6.0 * v[300:]])])
    pts = np.concatenate([pts[~shadow], walls])
    roof = np.concatenate([roof[~shadow], np.zeros(len(walls), bool)])
    wall = np.zeros(len(pts), bool)
    wall[-len(walls):] = True
    pts -= pts.mean(axis=0)
    ground, _ = morphological_ground(pts, HybridSettings())
    assert not ground[roof].any()
    up = pts[:, 2] - pts[~roof & ~wall, 2].mean() > 1.5  # higher than any band reaches
    assert not ground[wall & up].any()
    assert ground[~roof & ~wall].mean() > 0.99


def test_a_deep_echo_does_not_shield_a_shallower_one_beside_it():
    """Echoes come in twos and threes a few metres apart. A deep one (11 m down, inside a
    strip) was the lowest cell in the window of a shallower one (5 m down, just beyond
    the strip's edge), which therefore passed the low-blunder test and stayed ground: the
    test runs again without the blunders it found (LOW_ROUNDS). Simulated urban flight,
    seed 0: such pairs sank its rolling DEM by metres over 20 m around them."""
    rng = np.random.default_rng(1)
    pts = _flat(rng, (0.0, 2.0), (30.0, 42.0))
    pts = np.concatenate([pts, [[10.2, 3.5, -11.0], [12.4, 0.8, -5.0]]])
    ground, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings())
    assert not ground[-2:].any()
    assert ground[:-2].all()


def test_a_lone_echo_far_out_and_a_few_metres_down_leaves_the_ground():
    """A lone echo at a strip's corner, 3.6 m below flat ground that lies 18 m from it
    (simulated urban flight, seed 1): with the ground allowed to fall 0.1 per metre
    towards it (3.8 m there) it stayed ground and sank the rolling DEM; at lone_slope 0.05
    it leaves. A lone point 1 m below the ground 18 m off stays."""
    rng = np.random.default_rng(5)
    pts = _flat(rng, (0.0, 0.0), (30.0, 40.0))
    lone = np.array([[48.0, 20.0, -3.6]])
    pts = np.concatenate([pts, lone])
    ground, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings())
    assert not ground[-1] and ground[:-1].all()
    loose, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings(lone_slope=0.1))
    assert loose[-1]
    pts[-1, 2] = -1.0
    ground, _ = morphological_ground(pts - pts.mean(axis=0), HybridSettings())
    assert ground[-1]
