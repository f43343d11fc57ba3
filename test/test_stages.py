"""One cloud through the detector's stage (what obstacle_detector and replay run on each
message): points kept that have no return (`input.keep_non_finite`)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.config import ObstacleDetectorConfig, replace
from lidar_obstacles.io.pointcloud2 import read_points
from lidar_obstacles.ros import messages
from lidar_obstacles.ros.stages import DetectorStage


def test_kept_points_without_a_return_are_noise_never_ground_and_not_counted():
    """An organized scan of 40 x 50 points whose every fifth point had no return (x, y, z
    NaN). With `input.keep_non_finite` the outputs keep them: all in the `obstacles`
    cloud as noise (7) with no height above ground; the stats count the finite points."""
    rng = np.random.default_rng(0)
    points = np.zeros((40, 50), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    points["x"], points["y"] = np.meshgrid(np.arange(50) * 0.8, np.arange(40) * 0.8)
    points["z"] = rng.normal(0, 0.02, (40, 50))
    points["z"][10:16, 20:26] += 5.0  # a box on flat ground
    missing = (np.arange(2000) % 5 == 3).reshape(40, 50)
    for axis in "xyz":
        points[axis][missing] = np.nan
    msg = messages.cloud(points, messages.header(1_000_000_000, "map"))
    cfg = replace(ObstacleDetectorConfig(), {"input.keep_non_finite": True})
    out, stats = DetectorStage(cfg).process(msg)
    clouds = {name: read_points(m, keep_non_finite=True) for name, m in out
              if name in ("ground", "obstacles")}
    n_missing = int(missing.sum())
    assert stats["points_in"] == 2000 - n_missing
    assert stats["ground"] + stats["obstacles"] == 2000
    assert {k: len(v) for k, v in clouds.items()} == {k: stats[k] for k in clouds}
    assert np.isfinite(clouds["ground"]["x"]).all() and (clouds["ground"]["class"] == 2).all()
    gone = np.isnan(clouds["obstacles"]["x"])
    assert gone.sum() == n_missing
    assert (clouds["obstacles"]["class"][gone] == 7).all()
    assert np.isnan(clouds["obstacles"]["height_above_ground"][gone]).all()
    assert (stats["classes"][missing.ravel()] == 7).all()


@pytest.mark.parametrize("position, orientation, said", [
    ([0.0, 0.0, 50.0], [0.0, 0.0, 0.0, 0.0], "zero quaternion"),
    ([0.0, np.nan, 50.0], [0.0, 0.0, 0.0, 1.0], "not finite"),
    ([np.inf, 0.0, 50.0], [0.0, 0.0, 0.0, 1.0], "not finite"),
    ([0.0, 0.0, 50.0], [0.0, np.nan, 0.0, 1.0], "not finite"),
])
def test_an_odometry_pose_that_cannot_place_a_cloud_is_left_out(position, orientation, said):
    # used as it came, a zero quaternion put every point of the cloud at NaN: published as
    # 43 742 noise points at NaN, counted as processed
    from lidar_obstacles.ros.node_base import PoseBuffer
    from lidar_obstacles.ros.stages import Pose

    poses = PoseBuffer()
    good = Pose(10**9, np.array([1.0, 2.0, 50.0]), np.array([0.0, 0.0, 0.0, 1.0]), "odom")
    assert poses.add(good) is None
    bad = Pose(10**9 + 10**7, np.array(position), np.array(orientation), "odom")
    problem = poses.add(bad)
    assert problem is not None and said in problem
    assert poses.nearest(10**9 + 10**7, 0.2) is good  # the good one stands in


def test_frame_warnings_say_when_clouds_and_odometry_do_not_fit():
    from lidar_obstacles.ros.stages import Pose, moving_frame_warning

    pose = Pose(0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), "odom", "base_link")
    # in the body's frame: fine with odometry, a moving frame without it
    assert moving_frame_warning("base_link", pose, True) is None
    assert "use_odometry is false" in moving_frame_warning("base_link", pose, False)
    # already in the odometry's frame: nothing to say either way
    assert moving_frame_warning("odom", pose, True) is None
    assert moving_frame_warning("/odom", pose, False) is None
    # a third frame: placed as if it were the body's, which a tilted mount breaks (no tf)
    said = moving_frame_warning("lidar_link", pose, True)
    assert "'lidar_link'" in said and "no tf" in said and "'base_link'" in said
    assert moving_frame_warning("lidar_link", pose, False) is None
    # odometry without a child frame tells nothing
    anonymous = Pose(0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), "odom", "")
    assert moving_frame_warning("lidar_link", anonymous, True) is None
