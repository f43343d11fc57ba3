"""The rolling DEM thins each message's ground (`thinning.keep`) and holds check points out
of it (`thinning.check_points`) to measure itself, as the paper measured its DEMs."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.config import DemBuilderConfig, replace
from lidar_obstacles.core.dem import CheckPoints, DemGrid
from lidar_obstacles.core.pipeline import CHECK_MESSAGES, DemPipeline


def _ground(seed: int, n: int = 20000) -> np.ndarray:
    """A tilted plane z = 10 + 0.1 x with 2 cm noise over 100 x 100 m, (n, 3) m."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 100, (n, 2))
    return np.column_stack([xy, 10 + 0.1 * xy[:, 0] + rng.normal(0, 0.02, n)])


def _pipeline(**settings) -> DemPipeline:
    return DemPipeline(replace(DemBuilderConfig(), {"dem.interpolation": "idw",
                                                    "dem.extent": 0.0, **settings}))


def test_check_points_are_held_out_and_measure_the_dem():
    pipe = _pipeline()
    for i in range(3):
        pipe.add_ground(_ground(i))
    # 100 per message held out, the rest in the DEM
    assert len(pipe.checks.xyz) == 300
    assert int(pipe.dem.snapshot().count.sum()) == 3 * (20000 - 100)
    stats = pipe.check_accuracy()
    assert stats["check_n"] == 300
    # a 1 m cell's mean against a point in it: the noise and at most 0.05 m of slope
    assert 0.01 < stats["check_rmse_m"] < 0.05
    assert stats["check_r2"] > 0.99
    # a DEM one metre off is measured one metre off
    grid = pipe.dem.snapshot()
    shifted = DemGrid(grid.elevation + 1.0, grid.interpolated, grid.count, grid.origin,
                      grid.resolution, grid.reason)
    assert pipe.checks.accuracy(shifted)["check_rmse_m"] == pytest.approx(1.0, abs=0.05)


def test_thinning_keep_and_the_check_points_of_the_last_messages_only():
    pipe = _pipeline(**{"thinning.keep": 0.2, "thinning.check_points": 50})
    for i in range(CHECK_MESSAGES + 5):
        pipe.add_ground(_ground(i, 5000))
    assert len(pipe.checks.xyz) == CHECK_MESSAGES * 50  # bounded: the newest only
    kept = int(pipe.dem.snapshot().count.sum())
    assert kept == pytest.approx((CHECK_MESSAGES + 5) * 0.2 * (5000 - 50), rel=0.01)
    assert pipe.check_accuracy()["check_rmse_m"] < 0.06


def test_no_check_points_and_empty_grids_measure_nothing():
    pipe = _pipeline(**{"thinning.check_points": 0})
    pipe.add_ground(_ground(0, 1000))
    assert int(pipe.dem.snapshot().count.sum()) == 1000
    assert pipe.check_accuracy() == {"check_rmse_m": None, "check_r2": None, "check_n": 0}
    far = CheckPoints(10)
    far.add(np.array([[1e6, 1e6, 0.0]]))  # outside the grid
    assert far.accuracy(pipe.dem.snapshot())["check_n"] == 0


def test_changing_the_check_points_at_runtime_starts_a_new_set():
    pipe = _pipeline()
    pipe.add_ground(_ground(0, 2000))
    pipe.reconfigure(replace(pipe.cfg, {"thinning.check_points": 10}))
    pipe.add_ground(_ground(1, 2000))
    assert len(pipe.checks.xyz) == 10 and pipe.checks.capacity == CHECK_MESSAGES * 10


def test_check_points_find_their_cell_from_the_grids_own_origin():
    """Check point (x, y) lies in the cell of column floor((x - origin x) / res) and row
    floor((y - origin y) / res); the origin's x and y differ here, as a real survey's
    do (the flights above start near (0, 0), where x and y could be swapped unseen)."""
    elevation = np.array([[1.0, np.nan, 3.0], [4.0, 5.0, 6.0]], np.float32)
    grid = DemGrid(elevation, np.zeros((2, 3), np.uint8), np.ones((2, 3), np.uint32),
                   np.array([100.0, 200.0]), 2.0)
    checks = CheckPoints(10)
    checks.add(np.array([[101.0, 201.0, 1.0],    # cell (row 0, col 0) = 1: error 0
                         [105.5, 203.9, 7.0],    # cell (1, 2) = 6: error 1
                         [102.5, 200.5, 3.0],    # cell (0, 1) unknown: left out
                         [99.9, 201.0, 5.0],     # west of the grid
                         [103.0, 204.0, 0.0]]))  # north of it (row 2 of 2)
    stats = checks.accuracy(grid)
    assert stats["check_n"] == 2
    assert stats["check_rmse_m"] == pytest.approx(np.sqrt(0.5))
    # reference heights 1 and 7 (mean 4, SS_tot 18), SS_res 1
    assert stats["check_r2"] == pytest.approx(1 - 1 / 18)


def test_the_newest_check_points_are_kept():
    """`capacity` bounds them, and it is the oldest that go: over a long flight the
    oldest have left the rolling window, where they would measure nothing."""
    checks = CheckPoints(2)
    for k in range(3):
        checks.add(np.array([[k, 0.0, 0.0], [k, 1.0, 0.0]]))
    assert checks.xyz.tolist() == [[2.0, 0.0, 0.0], [2.0, 1.0, 0.0]]
