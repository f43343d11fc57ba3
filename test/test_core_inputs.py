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


def test_far_points_keep_every_point_of_the_real_data():
    from lidar_obstacles.core.ground import far_points
    from lidar_obstacles.io.las import read_las

    from conftest import DATA

    files = sorted(DATA.rglob("*.laz")) if DATA.is_dir() else []
    if not files:
        pytest.skip(f"no data in {DATA}")
    for path in files:
        assert not far_points(read_las(path).xyz[:, :2]).any(), path.name


def test_a_cloud_too_wide_for_the_raster_is_refused_with_the_reason():
    # two dense patches 8 km apart: no stray point, but 64 M cells of 1 m
    a, b = _cloud(0, 20000), _cloud(1, 20000) + [8000.0, 8000.0, 0.0]
    with pytest.raises(CloudFormatError, match="spans .* m, more than .* cells"):
        ObstacleDetector(DET).process(np.vstack([a, b]))


@pytest.mark.parametrize("window", [1.0, 2.0, 2.9])
def test_small_ground_windows_work(window):
    # the opening's work arrays also serve the 6 m rim window: they must fit both
    res = ObstacleDetector(replace(DET, {"ground.window": window})).process(_cloud(0))
    assert res.ground.any()


def test_rejected_clouds_are_counted_by_the_kind_of_their_error():
    from lidar_obstacles.errors import reason_key

    assert reason_key("cloud has no 'z' field (fields: x, y)") == "cloud has no 'z' field"
    assert reason_key("cloud has 3000000 points, more than input.max_points=2000000") == \
        "cloud has 3000000 points, more than input.max_points=2000000"
    assert reason_key("point_step 8: smaller than its fields") == "point_step 8"
    assert len(reason_key("x" * 200)) == 80
