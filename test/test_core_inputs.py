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
