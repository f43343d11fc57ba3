"""The same scene presented differently gives the same answer: the points in another order,
the cloud moved by whole metres (survey coordinates), every point twice."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.config import ObstacleDetectorConfig
from lidar_obstacles.core.ground import classify_ground

CFG = ObstacleDetectorConfig()


def _ground(xyz, context=None):
    return classify_ground(xyz, tiling=CFG.tiling, ground=CFG.ground, tin=CFG.tin,
                           ransac=CFG.ransac, context_xyz=context,
                           rng=np.random.default_rng(0))


def _scene(seed=0, n=30000, size=90.0):
    """Rolling terrain with a flat-roofed building and a few bushes, in UTM-like
    coordinates (metres)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, size, (n, 2))
    z = 40.0 + 3.0 * np.sin(xy[:, 0] / 15.0) + 0.05 * xy[:, 1] + rng.normal(0, 0.03, n)
    roof = (xy[:, 0] > 30) & (xy[:, 0] < 50) & (xy[:, 1] > 30) & (xy[:, 1] < 45)
    z[roof] += 7.0
    bush = rng.random(n) < 0.03
    z[bush] += rng.uniform(0.3, 3.0, bush.sum())
    return np.column_stack([xy, z]) + [512000.0, 5402000.0, 250.0]


def test_the_ground_does_not_depend_on_the_order_of_the_points():
    # The filter was centred on the mean of every k-th point: a shuffled cloud moved the
    # centre, and the float32 rounding of the in-painted surface with it.
    xyz = _scene()
    first = _ground(xyz)
    for seed in range(3):
        order = np.random.default_rng(seed).permutation(len(xyz))
        again = _ground(xyz[order])
        np.testing.assert_array_equal(again.ground, first.ground[order])
        np.testing.assert_array_equal(again.height_above_ground,
                                      first.height_above_ground[order])
