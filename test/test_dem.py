"""DEM grids, thinning, ground source and the rolling DEM (lidar_obstacles.core.dem)."""
from __future__ import annotations


import numpy as np
import pytest

from conftest import data_file
from lidar_obstacles.config import DemBuilderConfig, ThinningConfig, replace
from lidar_obstacles.core.dem import RollingDem, accuracy, build_dem, thin, tin_curvature
from lidar_obstacles.errors import CloudFormatError, ConfigError


def _cfg(**updates) -> DemBuilderConfig:
    return replace(DemBuilderConfig(), updates)


def _plane_points(lo=0.0, hi=40.0, step=0.25, hole=None):
    """Points on z = 2 + 0.1 x + 0.05 y on a regular lattice (cell means = plane at the
    cells' mean positions), optionally without a disc hole (cx, cy, r)."""
    g = np.arange(lo + step / 2, hi, step)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    if hole is not None:
        xy = xy[np.hypot(xy[:, 0] - hole[0], xy[:, 1] - hole[1]) > hole[2]]
    return np.column_stack([xy, 2.0 + 0.1 * xy[:, 0] + 0.05 * xy[:, 1]])


def plane_at(xy):
    return 2.0 + 0.1 * xy[..., 0] + 0.05 * xy[..., 1]


def test_build_dem_plane_exact_with_measured_and_filled_cells():
    pts = _plane_points(hole=(20.0, 20.0, 5.0))
    grid = build_dem(pts, cfg=_cfg(**{"dem.resolution": 1.0, "dem.interpolation": "tin"}))
    assert grid.elevation.dtype == np.float32 and grid.interpolated.dtype == np.uint8
    assert grid.count.dtype == np.uint32 and grid.shape == (40, 40)
    assert np.array_equal(grid.origin, [0.0, 0.0]) and grid.resolution == 1.0
    centres = grid.cell_centres()
    full = grid.count == 16  # 4 x 4 lattice points: mean position = cell centre
    filled = grid.interpolated == 1
    assert filled.sum() > 50 and np.all(grid.count[filled] == 0)
    assert np.all(full | filled | (grid.count > 0))
    assert np.allclose(grid.elevation[full | filled], plane_at(centres[full | filled]),
                       atol=1e-4)
    # a cell cut by the hole's rim is the mean of its points, off-centre by < half a cell
    assert np.allclose(grid.elevation, plane_at(centres), atol=0.1 * 0.5)
    assert grid.reason == ""


def test_origin_aligned_and_rows_are_y():
    pts = np.array([[10.3, 20.7, 1.0], [13.9, 20.2, 2.0], [10.1, 24.6, 3.0], [13.2, 24.9, 4.0]])
    grid = build_dem(pts, cfg=_cfg(**{"dem.resolution": 2.0}))
    assert np.array_equal(grid.origin, [10.0, 20.0])
    assert grid.shape == (3, 2)  # y 20..26 -> 3 rows, x 10..14 -> 2 cols
    assert grid.elevation[0, 0] == 1.0 and grid.elevation[0, 1] == 2.0
    assert grid.elevation[2, 0] == 3.0 and grid.elevation[2, 1] == 4.0


def test_fill_distance_limits_interpolation():
    left = _plane_points(0, 10, 0.5)
    right = left + [60.0, 0.0, 0.0]
    right[:, 2] = plane_at(right[:, :2])
    pts = np.vstack([left, right])
    grid = build_dem(pts, cfg=_cfg(**{"dem.interpolation": "idw", "dem.fill_distance": 5.0}))
    col_x = grid.origin[0] + (np.arange(grid.shape[1]) + 0.5) * grid.resolution
    middle = (col_x > 16) & (col_x < 54)
    assert np.isnan(grid.elevation[:, middle]).all()
    near = (col_x > 10) & (col_x < 14.5)
    assert np.isfinite(grid.elevation[:, near]).all()
    assert (grid.interpolated[:, near] == 1).all()


def test_fill_distance_is_inclusive():
    """Empty cells within `dem.fill_distance` of a measured cell (centre to centre) are
    filled, at exactly that distance too; farther ones stay unknown. Measured columns
    0-2 and 8-10 of 1 m cells, a gap of columns 3-7 (1, 2, 3, 2, 1 cells from the data)."""
    xs = np.r_[0:3, 8:11] + 0.5
    xy = np.stack(np.meshgrid(xs, np.arange(3) + 0.5), axis=-1).reshape(-1, 2)
    pts = np.column_stack([xy, plane_at(xy)])
    grid = build_dem(pts, cfg=_cfg(**{"dem.resolution": 1.0, "dem.interpolation": "idw",
                                      "dem.fill_distance": 2.0}))
    assert np.array_equal(grid.origin, [0.0, 0.0]) and grid.shape == (3, 11)
    known = np.isfinite(grid.elevation).all(axis=0)
    assert known.tolist() == [True] * 5 + [False] + [True] * 5
    filled = [False] * 3 + [True, True, False, True, True] + [False] * 3
    assert grid.interpolated.all(axis=0).tolist() == filled


def test_fill_distance_zero_keeps_the_measured_cells_only():
    """`dem.fill_distance` 0 (its range's low end): nothing is interpolated. build_dem
    raised a TypeError (float slice bounds) here; the end-to-end benchmark uses it to find
    the cells inside the data."""
    xs = np.r_[0:3, 8:11] + 0.5
    xy = np.stack(np.meshgrid(xs, np.arange(3) + 0.5), axis=-1).reshape(-1, 2)
    pts = np.column_stack([xy, plane_at(xy)])
    grid = build_dem(pts, cfg=_cfg(**{"dem.resolution": 1.0, "dem.fill_distance": 0.0}))
    assert grid.shape == (3, 11)
    assert np.isfinite(grid.elevation).all(axis=0).tolist() == [True] * 3 + [False] * 5 + [True] * 3
    assert not grid.interpolated.any()
    assert grid.count.sum() == len(pts)


@pytest.mark.parametrize("method", ["tin", "idw", "kriging", "rbf", "rbfnn"])
def test_degenerate_ground_gives_reason_not_crash(method):
    cfg = _cfg(**{"dem.interpolation": method})
    empty = build_dem(np.zeros((0, 3)), cfg=cfg)
    assert empty.shape == (0, 0) and "no ground" in empty.reason
    two = build_dem(np.array([[0.5, 0.5, 1.0], [3.5, 0.5, 2.0]]), cfg=cfg)
    assert "only 2" in two.reason and (two.interpolated == 0).all()
    assert np.nansum(two.count) == 2
    line = np.column_stack([np.linspace(0, 20, 50), np.linspace(0, 10, 50), np.ones(50)])
    on_line = build_dem(line, cfg=cfg)
    assert "collinear" in on_line.reason and (on_line.interpolated == 0).all()
    same = build_dem(np.tile([[5.0, 5.0, 3.0]], (10, 1)), cfg=cfg)
    assert same.shape == (1, 1) and same.elevation[0, 0] == 3.0 and "only 1" in same.reason
    flat = _plane_points(0, 10, 0.5, hole=(5, 5, 2))
    flat[:, 2] = 7.0
    flat_grid = build_dem(flat, cfg=cfg)
    assert "flat" in flat_grid.reason
    assert np.allclose(flat_grid.elevation[np.isfinite(flat_grid.elevation)], 7.0)


def test_build_dem_rejects_huge_grids_and_bad_shapes():
    with pytest.raises(ConfigError):
        build_dem(np.array([[0.0, 0.0, 0.0], [1e5, 1e5, 0.0]]), cfg=_cfg())
    # beyond int64: the count said "DEM of -9223372036854775762 x ... cells"
    with pytest.raises(ConfigError, match=r"^DEM of 1 x 6e\+30 cells exceeds"):
        build_dem(np.array([[-3e30, 0.0, 0.0], [3e30, 0.0, 0.0]]), cfg=_cfg())
    with pytest.raises(CloudFormatError):
        build_dem(np.zeros((5, 2)), cfg=_cfg())


def test_grid_sample_bilinear_and_accuracy():
    grid = build_dem(_plane_points(), cfg=_cfg())
    xy = np.array([[5.2, 7.9], [30.0, 12.25], [100.0, 0.0]])
    got = grid.sample(xy)
    assert np.allclose(got[:2], plane_at(xy[:2]), atol=1e-4) and np.isnan(got[2])
    rmse, r2, n = accuracy(np.array([1.0, 2.0, 3.0, np.nan]), np.array([1.0, 2.0, 4.0, 1.0]))
    assert n == 3 and rmse == pytest.approx(np.sqrt(1 / 3)) and r2 == pytest.approx(1 - 9 / 42)


def test_thinning_counts_and_disjoint():
    pts = _plane_points(0, 20, 0.5)
    t = thin(pts, cfg=ThinningConfig(keep=0.2, check_points=100, seed=1))
    assert len(t.check) == 100 and len(t.keep) == round(0.2 * (len(pts) - 100))
    assert not np.intersect1d(t.keep, t.check).size
    again = thin(pts, cfg=ThinningConfig(keep=0.2, check_points=100, seed=1))
    assert np.array_equal(t.keep, again.keep)


def test_curvature_thinning_keeps_more_where_terrain_bends():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 40, (8000, 2))
    z = np.where(xy[:, 0] < 20, 0.0, 0.0)
    ditch = np.abs(xy[:, 0] - 30) < 3
    z[ditch] = -0.3 * (9 - (xy[ditch, 0] - 30) ** 2)  # a parabolic ditch
    pts = np.column_stack([xy, z])
    interior_flat = (xy[:, 0] > 5) & (xy[:, 0] < 20) & (xy[:, 1] > 5) & (xy[:, 1] < 35)
    assert tin_curvature(pts)[interior_flat].max() < 1e-9
    # on a tilted plane too, hull and uneven spacing and all (the inverse-distance mean
    # of the neighbours gave 0.05 m at the median there, 0.9 m at most)
    slope = np.column_stack([xy, 0.3 * xy[:, 0] + 0.1 * xy[:, 1]])
    assert tin_curvature(slope).max() < 1e-6
    cfg = ThinningConfig(method="curvature", keep=0.2, check_points=0, seed=2)
    kept = thin(pts, cfg=cfg).keep
    share_ditch = np.isin(np.flatnonzero(ditch), kept).mean()
    share_flat = np.isin(np.flatnonzero(~ditch), kept).mean()
    assert share_ditch > 1.5 * share_flat


def test_kmeans_ground_source_is_the_papers_kmeans():
    from lidar_obstacles.core.kmeans import kmeans_ground
    from lidar_obstacles.core.pipeline import DemPipeline

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 50, (3000, 2))
    z = np.where(rng.random(3000) < 0.3, rng.uniform(2, 10, 3000), rng.normal(0, 0.05, 3000))
    xyz = np.column_stack([xy, z])
    cfg = _cfg(**{"dem.ground_source": "kmeans"})
    ground = DemPipeline(cfg).ground_of(xyz, stamp=0.0, intensity=None)
    assert np.array_equal(ground, kmeans_ground(xyz, cfg=cfg.kmeans).ground)
    assert (z[ground] < 1.0).mean() > 0.95 and ground[z < 0.2].mean() > 0.8


def test_rolling_dem_window_follows_vehicle_and_is_bounded():
    cfg = _cfg(**{"dem.extent": 20.0, "dem.resolution": 1.0, "dem.interpolation": "idw"})
    dem = RollingDem(cfg)
    assert dem.snapshot().shape == (0, 0)
    pts = _plane_points(0, 100, 0.5)
    strips = []
    for x0 in range(0, 80, 10):
        strip = pts[(pts[:, 0] >= x0) & (pts[:, 0] < x0 + 15)]
        strips.append(strip)
        vehicle = np.array([x0 + 7.5, 50.0])
        dem.update(strip, vehicle, float(x0))
        snap = dem.snapshot()
        assert snap.shape == (20, 20)  # bounded: the window never grows
        # 20 cells centred on the vehicle's cell: x from floor(x0 + 7.5) - 10 = x0 - 3
        lo = snap.origin
        hi = lo + np.array(snap.shape[::-1]) * snap.resolution
        assert np.array_equal(lo, [x0 - 3.0, 40.0])
        assert np.all(lo <= vehicle) and np.all(vehicle < hi)
        if x0 >= 20:  # the start (7.5, 50) is more than half a window behind: left
            assert lo[0] > 7.5
        # what the window holds: exactly the points seen inside it, older cells forgotten
        seen = sum(int(np.all((s[:, :2] >= lo) & (s[:, :2] < hi), axis=1).sum())
                   for s in strips)
        assert snap.count.sum() == seen
    assert dem.stamp == 70.0
    snap = dem.snapshot()
    measured = snap.count > 0
    assert measured.mean() > 0.5 and np.isfinite(snap.elevation).all()
    truth = plane_at(snap.cell_centres())
    assert np.allclose(snap.elevation[measured], truth[measured], atol=1e-4)
    assert np.allclose(snap.elevation[~measured], truth[~measured], atol=0.5)  # IDW


def test_rolling_dem_refines_cells_and_fills_gaps():
    cfg = _cfg(**{"dem.extent": 0.0, "dem.resolution": 1.0, "dem.interpolation": "tin"})
    dem = RollingDem(cfg)
    a = _plane_points(0, 30, 0.5, hole=(15, 15, 4))
    dem.update(a, None, 1.0)
    first = dem.snapshot()
    gap = first.interpolated == 1
    assert gap.sum() > 20
    assert np.allclose(first.elevation[gap], plane_at(first.cell_centres()[gap]), atol=1e-3)
    # the gap measured later: those cells become measured, counts add up
    b = _plane_points(0, 30, 0.5)
    b = b[np.hypot(b[:, 0] - 15, b[:, 1] - 15) <= 4]
    dem.update(b + [0.0, 0.0, 1.0], None, 2.0)  # 1 m higher: the mean moves
    second = dem.snapshot()
    assert (second.interpolated[gap] == 0).all() and (second.count[gap] > 0).all()
    # the whole-flight grid grows when data arrive elsewhere
    far = _plane_points(100, 110, 0.5)
    dem.update(far, None, 3.0)
    third = dem.snapshot()
    assert third.origin[0] <= 0 and third.origin[0] + third.shape[1] >= 110
    assert third.count.sum() == len(a) + len(b) + len(far)


def test_rolling_dem_whole_flight_respects_max_cells():
    """Past dem.max_cells the whole-flight grid becomes a window of that many cells around
    the latest data: each 20 x 20 m patch is then in it whole, the earlier ones gone (a
    window left at the flight's start, or an empty grid, is small enough too)."""
    cfg = _cfg(**{"dem.extent": 0.0, "dem.max_cells": 2500, "dem.interpolation": "idw"})
    dem = RollingDem(cfg)
    for x0 in (0.0, 200.0, 400.0):
        patch = _plane_points(x0, x0 + 20, 1.0)
        dem.update(patch, None, x0)
        snap = dem.snapshot()
        assert snap.elevation.size <= 2500
        assert snap.count.sum() == len(patch) == 400  # all of the latest, none of the rest
        assert (snap.origin <= x0).all() and (snap.origin + snap.shape[::-1] >= x0 + 20).all()
        measured = snap.count > 0
        assert np.allclose(snap.elevation[measured], plane_at(snap.cell_centres()[measured]),
                           atol=1e-4)


def test_real_isprs_dem_from_reference_ground():
    from lidar_obstacles.io.las import read_las

    cloud = read_las(data_file("isprs/samp52-utm.laz"))
    ground = cloud.xyz[cloud.points["classification"] == 2]
    t = thin(ground, cfg=ThinningConfig(keep=0.8, check_points=100, seed=0))
    grid = build_dem(ground[t.keep], cfg=_cfg(**{"dem.resolution": 2.0}))
    rmse, r2, n = accuracy(grid.sample(ground[t.check, :2]), ground[t.check, 2])
    assert n >= 90 and rmse < 1.0 and r2 > 0.99


def _count_calls(monkeypatch, name: str) -> list:
    """Calls of lidar_obstacles.core.dem.<name> from now on (one entry per call)."""
    from lidar_obstacles.core import dem as dem_mod

    calls: list = []
    real = getattr(dem_mod, name)

    def counting(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(dem_mod, name, counting)
    return calls


def _gapped_plane(rng: np.random.Generator, shift: float = 0.0) -> np.ndarray:
    """(N, 3) points of the plane z = 0.1 x over 40 x 40 m (+ shift in x), with 2 m strips
    every 8 m left empty for the interpolator to fill."""
    xy = rng.uniform(0, 40, (1500, 2)) + [shift, 0.0]
    xy = xy[(xy[:, 0] % 8) > 2]
    return np.column_stack([xy, 0.1 * xy[:, 0]])


def _rolling_60m(method: str) -> RollingDem:
    """A rolling DEM of 1 m cells in a 60 m window, filled by `method`."""
    return RollingDem(replace(DemBuilderConfig(), {"dem.interpolation": method,
                                                   "dem.resolution": 1.0, "dem.extent": 60.0}))


def test_rolling_kriging_refits_its_variogram_every_ten_updates(monkeypatch):
    fits = _count_calls(monkeypatch, "kriging_variogram")
    roll = _rolling_60m("kriging")
    cfg, rng = roll.cfg, np.random.default_rng(0)
    for i in range(12):
        roll.update(_gapped_plane(rng), np.array([20.0, 20.0]), float(i))
        roll.refill()  # as if the DEM were read after every message
    assert len(fits) == 2  # refills 1 and 11
    roll.cfg = replace(cfg, {"kriging.neighbours": 24})  # new parameters: refit at once
    roll.update(_gapped_plane(rng), np.array([20.0, 20.0]), 12.0)
    roll.refill()
    assert len(fits) == 3
    filled = roll.snapshot()
    centres = filled.cell_centres()
    inside = np.all((centres > 0.5) & (centres < 39.5), axis=-1)  # kriging only interpolates
    known = np.isfinite(filled.elevation) & inside
    assert known.sum() > 1400
    centres = centres[known]
    # cells hold the mean of their points, so a plane is reproduced to within its slope
    # times the offset of that mean from the centre (< 0.05 m here)
    assert np.allclose(filled.elevation[known], 0.1 * centres[:, 0], atol=0.06)


def test_rolling_dem_fills_gaps_when_read_not_per_message(monkeypatch):
    calls = _count_calls(monkeypatch, "interpolate")
    roll, rng = _rolling_60m("idw"), np.random.default_rng(1)
    for i in range(5):  # the window follows the vehicle between reads
        roll.update(_gapped_plane(rng, shift=2.0 * i), np.array([20.0 + 2 * i, 20.0]), i)
    assert calls == []
    grid = roll.snapshot()
    assert len(calls) == 1
    gap = (grid.interpolated == 1) & np.isfinite(grid.elevation)
    assert gap.any()
    rows, cols = grid.elevation.shape
    x = grid.origin[0] + (np.arange(cols) + 0.5) * grid.resolution
    y = grid.origin[1] + (np.arange(rows) + 0.5) * grid.resolution
    inside = ((x > 3) & (x < 46))[None, :] & ((y > 1) & (y < 39))[:, None]  # not past the data
    expect = np.broadcast_to(0.1 * x, grid.elevation.shape)
    assert (gap & inside).sum() > 100
    assert np.allclose(grid.elevation[gap & inside], expect[gap & inside], atol=0.15)
    roll.snapshot()
    assert len(calls) == 1  # nothing new: nothing to fill


def test_dem_takes_bare_earth_from_the_detector_ground():
    from lidar_obstacles.core.pipeline import DemPipeline, bare_earth, bare_earth_of

    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [0.0, 1.0, 0.4], [1.0, 1.0, 3.0]])
    ground = np.array([True, True, True, False])
    hag = np.array([0.0, 0.1, 0.4, 3.0], np.float32)
    dem = DemBuilderConfig().dem
    assert bare_earth_of(xyz, ground, hag, dem).tolist() == [True, True, False, False]
    assert bare_earth(xyz[:3], hag[:3], dem).tolist() == [True, True, False]
    no_band = replace(DemBuilderConfig(), {"dem.ground_band": 0.0}).dem
    assert bare_earth_of(xyz, ground, hag, no_band).tolist() == ground.tolist()
    # flat ground with grass 0.3 m high inside the filter's band: the DEM stays on the earth
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 40, (20000, 2))
    z = np.where(rng.random(20000) < 0.3, 0.3, 0.0) + rng.normal(0, 0.01, 20000)
    pipe = DemPipeline(replace(DemBuilderConfig(), {"dem.interpolation": "idw",
                                                    "dem.resolution": 1.0}))
    pipe.process(np.column_stack([xy, z]), stamp=0.0)
    grid = pipe.dem.snapshot()
    assert abs(float(np.nanmedian(grid.elevation))) < 0.03
    assert np.nanmean(grid.elevation) < 0.05  # with all the detector's ground: ~0.09


def test_band_widens_on_steep_sparse_ground_only():
    from lidar_obstacles.core.dem import band_allowance
    from lidar_obstacles.core.pipeline import bare_earth

    rng = np.random.default_rng(8)
    # ISPRS-like: a 1:2 slope, one point per 4 m^2 (spacing 2 m); the filter's surface is
    # off by up to 0.35 m there (in-painted between the points). The band becomes
    # 0.15 + 0.5 x ~0.5 m (spacing 2 m x half the slope: the median rise to 4 cells).
    xy = rng.uniform(0, 200, (10000, 2))
    slope = np.column_stack([xy, 0.5 * xy[:, 0]])
    allowance = band_allowance(slope, np.zeros(len(xy), np.float32))
    assert 0.4 < np.median(allowance) < 0.7
    off = rng.uniform(0.0, 0.35, len(xy)).astype(np.float32)
    dem = DemBuilderConfig().dem
    assert bare_earth(slope, off, dem).mean() > 0.95
    fixed = replace(DemBuilderConfig(), {"dem.band_slope": 0.0}).dem
    assert bare_earth(slope, off, fixed).mean() < 0.5
    # dense (0.2 m) flat ground: the band stays 0.15 m and grass 0.3 m up still goes
    xy = rng.uniform(0, 40, (40000, 2))
    flat = np.column_stack([xy, rng.normal(0, 0.01, len(xy))])
    assert np.percentile(band_allowance(flat, np.zeros(len(xy))), 99) < 0.02
    grass = np.full(len(xy), 0.3, np.float32)
    assert not bare_earth(flat, grass, dem).any()
    # a NaN height (no surface there) counts as on it; too few points, no allowance
    assert band_allowance(flat[:1], np.zeros(1)).tolist() == [0.0]
    assert np.all(band_allowance(flat[:5], np.full(5, np.nan)) == 0.0)


def _hill(rng: np.random.Generator, n: int = 40000, size: float = 100.0) -> np.ndarray:
    """Ground points (n, 3) on a smooth hill: z = 12 exp(-r^2 / 30^2) around the centre of
    a size x size m square (slopes up to 0.34) plus 2 cm noise, ~4 points per m^2."""
    xy = rng.uniform(0.0, size, (n, 2))
    r2 = np.sum((xy - size / 2) ** 2, axis=1)
    return np.column_stack([xy, 12.0 * np.exp(-r2 / 900.0) + rng.normal(0, 0.02, n)])


def test_ground_blunders_drop_a_roof_in_a_gap_and_low_blunders_keep_the_hill():
    from lidar_obstacles.core.dem import ground_blunders

    rng = np.random.default_rng(3)
    hill = _hill(rng)
    # a gap 16 m across (a building's footprint) on the hill's flank, and in it a 10 x 10 m
    # roof 4 m above the ground around it: what kriging spread over the gap on 07CZ2
    centre = np.array([25.0, 50.0])
    hill = hill[np.max(np.abs(hill[:, :2] - centre), axis=1) > 8.0]
    ground_z = 12.0 * np.exp(-np.sum((centre - 50.0) ** 2) / 900.0)
    roof_xy = centre + rng.uniform(-5.0, 5.0, (400, 2))
    roof = np.column_stack([roof_xy, np.full(400, ground_z + 4.0)])
    # three multipath points 25 m under the ground, together (ISPRS samp41 has such)
    low = np.column_stack([rng.uniform(70, 71, (3, 2)), np.full(3, -25.0)])
    xyz = np.concatenate([hill, roof, low])
    drop = ground_blunders(xyz, max_area=400.0, rise=1.0, sink=10.0)
    assert drop[len(hill):].all()  # the roof and the low blunders
    assert not drop[:len(hill)].any()  # every point of the smooth hill stays
    # a patch larger than max_area is not judged (an upper terrace), nor anything with 0
    assert not ground_blunders(xyz, max_area=50.0, rise=1.0, sink=10.0)[len(hill):-3].any()
    assert not ground_blunders(xyz, max_area=0.0, rise=1.0, sink=10.0).any()


def test_ground_blunders_keep_steep_smooth_ground_and_a_pit():
    from lidar_obstacles.core.dem import ground_blunders

    rng = np.random.default_rng(4)
    # a 35-degree slope (rise 0.7 per m) 60 x 60 m, sparse as ISPRS (1 point per 2 m^2),
    # with an underpass ramp: a 10 x 10 m pit 5 m deep, its walls vertical
    xy = rng.uniform(0.0, 60.0, (1800, 2))
    z = 0.7 * xy[:, 0] + rng.normal(0, 0.05, 1800)
    pit = np.max(np.abs(xy - 30.0), axis=1) < 5.0
    z[pit] -= 5.0
    drop = ground_blunders(np.column_stack([xy, z]), max_area=400.0, rise=1.0, sink=10.0)
    assert not drop.any()


def test_bare_earth_in_the_rolling_dem_drops_a_patch_on_top_of_trees():
    """What `replay` hands the DEM: the detector's ground and its height above the ground
    surface. A tree crown taken for ground (hag 0: the detector's surface runs through
    it) in a canopy gap must not become a 6 m hill in the DEM."""
    from lidar_obstacles.core.pipeline import DemPipeline

    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 60.0, (30000, 2))
    gap = np.hypot(xy[:, 0] - 30.0, xy[:, 1] - 30.0) < 10.0
    ground = np.column_stack([xy[~gap], rng.normal(0, 0.02, int((~gap).sum()))])
    crown_xy = 30.0 + rng.uniform(-3.0, 3.0, (200, 2))
    crown = np.column_stack([crown_xy, 6.0 + rng.normal(0, 0.3, 200)])
    pts = np.concatenate([ground, crown])
    cfg = _cfg(**{"dem.interpolation": "kriging", "dem.resolution": 1.0})
    pipe = DemPipeline(cfg)
    pipe.add_ground(pts, stamp=0.0, height_above_ground=np.zeros(len(pts)))
    grid = pipe.dem.snapshot()
    assert np.nanmax(np.abs(grid.elevation)) < 0.2
    off = DemPipeline(replace(cfg, {"dem.patch_area": 0.0}))
    off.add_ground(pts, stamp=0.0, height_above_ground=np.zeros(len(pts)))
    assert np.nanmax(off.dem.snapshot().elevation) > 5.0  # what the test guards against


def test_ground_blunders_keep_ground_cut_off_on_a_slope():
    """A disc of real ground on a 0.5 slope, seen through a ring-shaped gap in the ground
    (canopy all around it): above the ground downhill, below the ground uphill, so not a
    patch standing on the terrain."""
    from lidar_obstacles.core.dem import ground_blunders

    rng = np.random.default_rng(6)
    xy = rng.uniform(0.0, 60.0, (14400, 2))  # 4 points per m^2
    r = np.hypot(xy[:, 0] - 30.0, xy[:, 1] - 30.0)
    xy = xy[(r < 3.0) | (r > 9.0)]
    xyz = np.column_stack([xy, 0.5 * xy[:, 0] + rng.normal(0, 0.02, len(xy))])
    assert not ground_blunders(xyz, max_area=400.0, rise=1.0, sink=10.0).any()


def test_a_rolling_window_keeps_the_cells_it_filled_when_it_moves():
    """The window moves with the vehicle; the cells a gap was filled in, still inside it,
    keep their values without being filled again (only the region of new data is)."""
    roll = _rolling_60m("tin")
    roll.update(_plane_points(0, 30, 0.5, hole=(15, 15, 4)), np.array([15.0, 15.0]), 1.0)
    first = roll.snapshot()
    gap = np.argwhere(first.interpolated == 1)
    assert len(gap) > 20
    at = first.origin + (gap[:, ::-1] + 0.5) * first.resolution  # x, y of the gap's cells
    # 10 m on: the gap stays inside the window, the new data lie 25 m from it
    g = np.arange(0.25, 10, 0.5)
    far = np.stack(np.meshgrid(g + 40.0, g), axis=-1).reshape(-1, 2)
    roll.update(np.column_stack([far, plane_at(far)]), np.array([25.0, 15.0]), 2.0)
    second = roll.snapshot()
    assert second.origin[0] == first.origin[0] + 10
    rc = np.floor((at - second.origin) / second.resolution).astype(int)[:, ::-1]
    values = second.elevation[rc[:, 0], rc[:, 1]]
    assert np.isfinite(values).all() and np.allclose(values, plane_at(at), atol=1e-3)


def test_data_added_twice_before_a_read_has_both_regions_filled():
    """Two updates, one north and one south (or east and west; either first), then one
    read: the empty cells beside both are filled (the region to fill is their union)."""
    for axis in (1, 0):  # y: rows, x: columns
        holes = [(15, 24), (15, 6)] if axis == 1 else [(24, 15), (6, 15)]
        one = _plane_points(0, 30, 0.5, hole=(*holes[0], 3))
        other = _plane_points(0, 30, 0.5, hole=(*holes[1], 3))
        halves = [one[one[:, axis] > 15], other[other[:, axis] <= 15]]
        for first, second in (halves, halves[::-1]):
            roll = RollingDem(_cfg(**{"dem.extent": 0.0, "dem.resolution": 1.0,
                                      "dem.interpolation": "tin", "dem.fill_distance": 4.0}))
            roll.update(first, None, 1.0)
            roll.update(second, None, 2.0)
            grid = roll.snapshot()
            for cx, cy in holes:
                c = int((cx - grid.origin[0]) / grid.resolution)
                r = int((cy - grid.origin[1]) / grid.resolution)
                assert grid.interpolated[r, c] == 1 and np.isfinite(grid.elevation[r, c])


@pytest.mark.parametrize("lo, hi", [((0.0, 0.0), (200.0, 200.0)), ((-57.3, 12.9), (2e4, 43.0)),
                                    ((5.0, 5.0), (5.0, 3e5)), ((1e5, -3e4), (1.02e5, -2.9e4))])
def test_the_resolution_said_to_fit_fits_edge_cells_and_all(lo, hi):
    # 200 x 200 m at 0.05 m was told "0.1 m", which needs 2001^2 cells, over 4 000 000;
    # a span of 0 on one axis failed on log10(0)
    import re

    from lidar_obstacles.config import DemBuilderConfig, replace
    from lidar_obstacles.core.dem import too_large_message

    cfg = replace(DemBuilderConfig(), {"dem.resolution": 0.05})
    said = too_large_message(np.array(lo), np.array(hi), cfg)
    r = float(re.search(r"coarsen dem.resolution to ([\d.e+-]+) m$", said).group(1))
    cells = np.prod(np.floor(np.array(hi) / r) - np.floor(np.array(lo) / r) + 1)
    assert cells <= cfg.dem.max_cells, said
    coarser_than_needed = r - 10.0 ** (np.floor(np.log10(r)) - 1)
    assert np.prod(np.floor(np.array(hi) / coarser_than_needed)
                   - np.floor(np.array(lo) / coarser_than_needed) + 1) > cfg.dem.max_cells
