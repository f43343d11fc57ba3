"""The core's entry points refuse malformed points with CloudFormatError, and the ground
filter behaves the same wherever it runs (the detector, the DEM's `detector` source)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.config import DemBuilderConfig, ObstacleDetectorConfig, replace
from lidar_obstacles.core.ground import _collinear_xy, classify_ground
from lidar_obstacles.core.kmeans import kmeans_ground
from lidar_obstacles.core.pipeline import DemPipeline, ObstacleDetector, bare_earth_of
from lidar_obstacles.errors import CloudFormatError

DET = ObstacleDetectorConfig()


def _cloud(seed: int, n: int = 4000) -> np.ndarray:
    """Gently sloping ground with a 6 m box on it, (n, 3) m."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 60, (n, 2)) + np.array([seed * 20.0, 0.0])
    z = 0.05 * xy[:, 0] + rng.normal(0, 0.02, n)
    box = (np.abs(xy[:, 0] - xy[:, 0].mean()) < 5) & (np.abs(xy[:, 1] - 30) < 5)
    z[box] += 6.0
    return np.column_stack([xy, z])


ENTRY_POINTS = {
    "detector": lambda xyz: ObstacleDetector(DET).process(xyz),
    "classify_ground": lambda xyz: classify_ground(xyz, tiling=DET.tiling, ground=DET.ground,
                                                   tin=DET.tin, ransac=DET.ransac),
    "dem": lambda xyz: DemPipeline(DemBuilderConfig()).process(xyz),
    "kmeans_ground": lambda xyz: kmeans_ground(xyz, cfg=DemBuilderConfig().kmeans),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_entry_points_refuse_six_columns_and_nan(entry):
    xyz = _cloud(0, 1000)
    with pytest.raises(CloudFormatError, match=r"\(N, 3\).*\(1000, 6\)"):
        ENTRY_POINTS[entry](np.column_stack([xyz, xyz]))  # not 2000 points
    xyz[17, 2] = np.nan
    with pytest.raises(CloudFormatError, match="1 of 1000 points have a NaN"):
        ENTRY_POINTS[entry](xyz)


def test_collinear_xy_judges_all_points_not_a_sample():
    # an organized 100 x 5000 scan: every 100th point is one column of it, a line
    gx, gy = np.meshgrid(np.arange(5000) * 0.1, np.arange(100) * 0.1, indexing="ij")
    grid = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    assert not _collinear_xy(grid)
    assert _collinear_xy(grid[::100])
    t = np.linspace(0, 1e3, 5000)
    assert _collinear_xy(np.column_stack([5e5 + t, 5.7e6 + 2 * t, t]))  # a UTM line
    assert _collinear_xy(np.tile([[3.0, 4.0, 5.0]], (10, 1)))  # one spot


def test_the_dem_finds_the_detectors_ground_cloud_after_cloud_with_ransac():
    # `replay` hands the detector's ground to the DEM when their ground settings agree;
    # the DEM alone must then find the same ground, the random stream included
    settings = {"ground.method": "ransac", "context.radius": 40.0}
    det = ObstacleDetector(replace(DET, settings))
    dem = DemPipeline(replace(DemBuilderConfig(), {**settings, "dem.ground_source": "detector"}))
    for i in range(4):
        xyz = _cloud(i)
        step = det.ground_step(xyz, stamp=0.1 * i)
        expected = bare_earth_of(xyz, step.ground, step.height_above_ground, dem.cfg.dem)
        assert np.array_equal(dem.ground_of(xyz, stamp=0.1 * i, intensity=None), expected)
        assert 0.5 < expected.mean() < 0.99


@pytest.mark.parametrize("stray", [[1e4, 1e4, 0.0], [1e30, 0.0, 0.0], [3e38, 3e38, 5.0]])
def test_a_stray_point_far_away_is_noise_and_costs_nothing(stray):
    # one multipath return kilometres off made the raster gigabytes (17 GB at 10 km)
    xyz = np.vstack([_cloud(0, 3000), stray])
    det = ObstacleDetector(DET)
    res = det.process(xyz)
    assert res.classes[-1] == 7 and not res.ground[-1]
    assert np.isnan(res.height_above_ground[-1])
    assert res.ground[:-1].mean() > 0.5  # the rest as without it
    alone = ObstacleDetector(DET).process(xyz[:-1])
    assert np.array_equal(res.classes[:-1], alone.classes)
    dem = DemPipeline(replace(DemBuilderConfig(), {"dem.ground_source": "detector"}))
    assert not dem.ground_of(xyz, stamp=0.0, intensity=None)[-1]


STRAY_Z = [5000.0, -5000.0, 1e12, 1e20, 3e38]


@pytest.mark.parametrize("z", STRAY_Z)
def test_stray_points_far_above_or_below_the_cloud_are_noise(z):
    # 50 returns 5 km up were a wire 5003 m above ground, 5 km down two of them ground
    xyz = _cloud(0, 3000)
    xyz[:50, 2] = z
    res = ObstacleDetector(DET).process(xyz)
    assert (res.classes[:50] == 7).all() and not res.ground[:50].any()
    assert np.isnan(res.height_above_ground[:50]).all()
    alone = ObstacleDetector(DET).process(xyz[50:])
    assert np.array_equal(res.classes[50:], alone.classes)
    for source in ("detector", "kmeans"):
        dem = DemPipeline(replace(DemBuilderConfig(), {"dem.ground_source": source}))
        ground = dem.ground_of(xyz, stamp=0.0, intensity=None)
        assert not ground[:50].any() and ground[50:].mean() > 0.5, source


def test_far_in_z_leaves_tall_structures_and_steep_terrain_alone():
    from lidar_obstacles.core.ground import far_points

    xyz = _cloud(0, 3000)
    xyz[:5, 2] = 900.0  # above the tallest building there is (828 m)
    assert not far_points(xyz).any()
    xyz[:5, 2] = 2000.0
    assert far_points(xyz)[:5].all()
    # a 2 km rise (4:1) at the edge of a 2 km footprint, three quarters of it flat
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 2000, (8000, 2))
    z = np.where(xy[:, 0] > 1500, (xy[:, 0] - 1500) * 4.0, 0.0)  # 2 km of rise
    assert not far_points(np.column_stack([xy, z])).any()


@pytest.mark.parametrize("columns, dtype", [(2, np.float64), (3, np.float64), (3, np.float32)])
def test_far_points_do_not_depend_on_the_order_of_the_points(columns, dtype):
    # The bounds came from every k-th point: a cloud in another order had other quartiles,
    # and points near a bound changed sides. Here 80 points lie around the bound in x (two
    # columns) or in z (three), as far as the quartiles of 60 000 points are, +-20 m.
    from lidar_obstacles.core.ground import FAR_IQRS, FAR_MARGIN, FAR_MARGIN_Z, far_points

    rng = np.random.default_rng(3)
    n = 60_000
    xyz = np.column_stack([rng.uniform(0, 200, n), rng.uniform(0, 100, n),
                           rng.normal(50, 10, n)])[:, :columns]
    near_bound = np.linspace(-20, 20, 80)
    if columns == 2:  # quartiles 50 and 150
        xyz[:80, 0] = 150 + FAR_IQRS * 100 + FAR_MARGIN + near_bound
    else:  # height quartiles 50 -+ 6.74, footprint 200 x 100
        xyz[:80, 2] = 56.74 + FAR_IQRS * 13.49 + FAR_MARGIN_Z + np.hypot(200, 100) + near_bound
    xyz = xyz.astype(dtype)
    far = far_points(xyz)
    assert 0 < far[:80].sum() < 80 and not far[80:].any()  # (the cloud tests what it should)
    for seed in range(5):
        order = np.random.default_rng(seed).permutation(n)
        assert np.array_equal(far_points(xyz[order]), far[order])


def test_far_points_keep_every_point_of_the_real_data():
    # the farthest point beyond 3 IQRs of its cloud's heights: 61 m (samp31), 42 m (AHN)
    from lidar_obstacles.core.ground import far_points
    from lidar_obstacles.io.las import read_las

    from conftest import DATA

    files = sorted(DATA.rglob("*.laz")) if DATA.is_dir() else []
    if not files:
        pytest.skip(f"no data in {DATA}")
    for path in files:
        xyz = read_las(path).xyz
        assert not far_points(xyz).any(), path.name
        # and in the scanner's order, as las2bag's slices of a survey come
        assert not any(far_points(xyz[i:i + 2000]).any() for i in range(0, len(xyz), 2000))


def test_a_cloud_too_wide_for_the_raster_is_refused_with_the_reason():
    # two dense patches 8 km apart: no stray point, but 64 M cells of 1 m
    a, b = _cloud(0, 20000), _cloud(1, 20000) + [8000.0, 8000.0, 0.0]
    with pytest.raises(CloudFormatError, match="spans .* m, more than .* cells"):
        ObstacleDetector(DET).process(np.vstack([a, b]))


def test_a_cloud_far_sparser_than_its_grid_is_gridded_coarser():
    """50 points spread over 5 x 5 km (a driver's millimetres taken for metres makes such
    clouds): 25 million cells of 1 m, in-painted, and the footprint's distance transform
    took 11-15 s and 3.6 GB a cloud in the detector and the DEM. Their grids now hold at
    most 64 cells per point (250 000 at least); a real scan stays on its cell."""
    import tracemalloc

    from lidar_obstacles.core.arrays import sparse_grid_cell

    assert sparse_grid_cell(1.0, np.zeros(2), np.full(2, 4999.0), 50) == 10.0
    # ISPRS's sparsest sample (samp53, ~0.17 points / m^2) and a UAV scan: unchanged
    assert sparse_grid_cell(1.0, np.zeros(2), np.array([450.0, 440.0]), 34_378) == 1.0
    assert sparse_grid_cell(0.5, np.zeros(2), np.array([30.0, 85.0]), 50_000) == 0.5
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 4999, (50, 2)), rng.uniform(0, 5, 50)])
    for run in (lambda: ObstacleDetector(DET).process(xyz, stamp=1.0),
                lambda: DemPipeline().process(xyz, stamp=1.0)):
        tracemalloc.start()
        try:
            result = run()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 200e6, peak  # bytes (3.6e9 before)
        assert result is not None


HUGE = {  # none has a stray point to drop: the cloud itself is the problem
    "two points 1e15 m apart": (np.array([[0.0, 0.0, 0.0], [1e15, 0.0, 0.0]]), "spans"),
    "halves 1e15 m apart": (np.vstack([_cloud(0, 2000), _cloud(1, 2000) + [1e15, 0, 0]]),
                            "spans"),
    "halves 1e15 m apart in z": (np.vstack([_cloud(0, 2000), _cloud(1, 2000) + [0, 0, 1e15]]),
                                 r"spans 1e\+15 m in z"),
    "halves 3.4e38 m either side": (np.vstack([_cloud(0, 2000) - [3.4e38, 0, 0],
                                               _cloud(1, 2000) + [3.4e38, 0, 0]]), "spans"),
    "a cloud 1e20 m up": (_cloud(0, 3000) + [0, 0, 1e20], r"lies 1e\+20 m from"),
}


@pytest.mark.parametrize("method", ["hybrid", "tin", "ransac", "kmeans"])
@pytest.mark.parametrize("name", sorted(HUGE))
def test_a_cloud_too_big_for_int64_cells_is_refused_with_the_reason(name, method):
    # its cell and voxel indices overflowed int64: IndexError, or garbage grids
    xyz, reason = HUGE[name]
    with pytest.raises(CloudFormatError, match=f"^the cloud {reason}"):
        if method == "kmeans":
            DemPipeline(replace(DemBuilderConfig(), {"dem.ground_source": "kmeans"})).process(xyz)
        else:
            ObstacleDetector(replace(DET, {"ground.method": method})).process(xyz)


@pytest.mark.parametrize("window", [1.0, 2.0, 2.9])
def test_small_ground_windows_work(window):
    # the opening's work arrays also serve the 6 m rim window: they must fit both
    cloud = _cloud(0)
    res = ObstacleDetector(replace(DET, {"ground.window": window})).process(cloud)
    off_box = cloud[:, 2] - 0.05 * cloud[:, 0] < 3.0  # (a box wider than the window is not
    assert res.ground[off_box].mean() > 0.99           # judged: the window cannot see it)


def test_rejected_clouds_are_counted_by_the_kind_of_their_error():
    # the kinds are /diagnostics and replay keys: one per size had them grow without end
    from lidar_obstacles.errors import reason_key

    assert reason_key("cloud has no 'z' field (fields: ('x', 'y'))") == "cloud has no 'z' field"
    # a cloud with no field at all: one key with the others (its "()" was left in it)
    assert reason_key("cloud has no 'x' field (fields: ())") == "cloud has no 'x' field"
    assert reason_key("cloud has 3000000 points, more than input.max_points=2000000") == \
        reason_key("cloud has 4407 points, more than input.max_points=100") == \
        "cloud has N points, more than input.max_points=N"
    assert reason_key("data has 106552 bytes, expected row_step 106559 * height 1 = 106559") \
        == "data has N bytes, expected row_step N * height N = N"
    assert reason_key("fields 'x' (bytes 0..3) and 'y' (from byte 2) overlap") == \
        "fields 'x' and 'y' overlap"  # not "fields 'x'"
    assert reason_key("the cloud spans 5000 x 8060 m, more than 25,000,000 cells of "
                      "ground.cell = 1.0 m: cut it into tiles (las2bag --tile-size)") == \
        "the cloud spans N x N m, more than N cells of ground.cell = N m"
    assert reason_key("the cloud lies 1e+20 m from the frame's origin, more than 1e+08 m: "
                      "its coordinates are not a scene") == \
        "the cloud lies N m from the frame's origin, more than N m"
    assert reason_key("field 'x' must be a single FLOAT32 or FLOAT64, got float16") == \
        "field 'x' must be a single FLOAT32 or FLOAT64, got float16"
    assert reason_key("point_step 8: smaller than its fields") == "point_step N"
    from lidar_obstacles.io.pointcloud2 import _check_xyz  # an x of count 3: what it got
    with pytest.raises(CloudFormatError) as err:             # was cut away, "…, got"
        _check_xyz(np.dtype([("x", "<f4", (3,)), ("y", "<f4"), ("z", "<f4")]))
    assert reason_key(str(err.value)) == ("field 'x' must be a single FLOAT32 or FLOAT64, "
                                          "got N x float32")
    assert len(reason_key("x" * 200)) == 80


def test_reasons_are_counted_apart_up_to_a_bound():
    # a flood of clouds each with its own unknown field made one /diagnostics key per cloud
    from lidar_obstacles.errors import MAX_REASON_KEYS, OTHER_REASONS, count_reason

    reasons: dict[str, int] = {}
    for name in ("alpha", "beta", "gamma", "delta") * 20:
        for i in range(12):
            count_reason(reasons, f"field '{name}{'x' * i}' has unknown datatype 9")
    count_reason(reasons, "cloud has 4407 points, more than input.max_points=100")
    assert len(reasons) == MAX_REASON_KEYS + 1 and sum(reasons.values()) == 4 * 20 * 12 + 1
    # 48 kinds, 20 clouds each: the first 32 apart, the other 16 and the last one together
    assert reasons[OTHER_REASONS] == (48 - MAX_REASON_KEYS) * 20 + 1
