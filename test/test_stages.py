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
    ([1e300, 0.0, 50.0], [0.0, 0.0, 0.0, 1.0], "beyond 1e+08 m"),
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


def test_slow_odometry_and_a_clock_gone_back_by_seconds_place_clouds_with_their_own_poses():
    """Poses 2 s apart (`odometry_max_age` 2) are no clock jumps: each places its cloud at
    once. After the clock went back 5 s, no pose of the earlier run (1 km off here) may
    place a cloud of the new one: all that was held goes."""
    from lidar_obstacles.ros.node_base import PoseBuffer
    from lidar_obstacles.ros.stages import Pose

    def at(s: float, x: float) -> Pose:
        return Pose(int(round(s * 1e9)), np.array([x, 0.0, 50.0]),
                    np.array([0.0, 0.0, 0.0, 1.0]), "map")

    slow = PoseBuffer()
    for s in (1.0, 3.0, 5.0, 7.0):
        slow.add(at(s, s))
        assert slow.nearest(int(s * 1e9), 2.0).position[0] == s
    poses = PoseBuffer()
    for k in range(201):  # 90-100 s at 20 Hz
        poses.add(at(90.0 + 0.05 * k, 90.0 + 0.05 * k))
    placed = []
    for k in range(60):  # the clock back at 95 s, the vehicle 1 km away
        s = 95.0 + 0.05 * k
        poses.add(at(s, s + 1000.0))
        if k >= 2:
            placed.append(poses.nearest(int(round(s * 1e9)), 0.2).position[0] - s)
    assert np.allclose(placed, 1000.0) and len(placed) == 58


def test_a_huge_quaternion_keeps_its_rotation():
    # (0, 0, 1e300, 1e300), a quarter turn about z: its norm overflowed to inf, and the
    # pose was taken for no rotation at all
    from lidar_obstacles.ros.stages import Pose

    for q in ([0.0, 0.0, 1e300, 1e300], [0.0, 0.0, 1e-300, 1e-300], [0.0, 0.0, 1.0, 1.0]):
        rot = Pose(1, np.zeros(3), np.array(q), "odom").rotation()
        assert np.allclose(rot @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), q


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


def _box_scene(stamp_ns: int):
    """A 40 m x 32 m flat cloud with a 5 m box on it: one obstacle object."""
    points = np.zeros((40, 50), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    points["x"], points["y"] = np.meshgrid(np.arange(50) * 0.8, np.arange(40) * 0.8)
    points["z"][10:16, 20:26] += 5.0
    return messages.cloud(points.ravel(), messages.header(stamp_ns, "map"))


def _lifetime(out) -> float:
    """The one lifetime of a cloud's boxes and labels, s."""
    array = dict(out)["obstacle_markers"]
    added = [m for m in array.markers if m.action == m.ADD]
    assert added, "the box should give markers"
    lifetimes = {m.lifetime.sec * 1_000_000_000 + m.lifetime.nanosec for m in added}
    assert len(lifetimes) == 1
    return lifetimes.pop() * 1e-9


@pytest.mark.parametrize("base, stamps_s, expected", [
    (2.0, [10.0, 10.1, 10.2], [2.0, 2.0, 2.0]),      # 10 Hz: the parameter
    (2.0, [10.0, 13.0, 14.0], [2.0, 9.0, 3.0]),      # a 3 s cloud: three intervals
    (2.0, [10.0, 1000.0], [2.0, 60.0]),              # a gap in a bag: capped at a minute
    (2.0, [10.0, 9.0], [2.0, 2.0]),                  # stamps going back: the parameter
    (0.0, [10.0, 13.0], [0.0, 0.0]),                 # 0: until replaced
])
def test_markers_vanish_after_their_lifetime_stretched_for_slow_clouds(base, stamps_s,
                                                                       expected):
    """`obstacles.marker_lifetime`: the boxes and labels of a cloud carry the lifetime, at
    least three times the interval between the last two stamps (up to 60 s), so stale
    boxes leave RViz when the input stops and slow clouds' boxes do not blink."""
    stage = DetectorStage(replace(ObstacleDetectorConfig(),
                                  {"obstacles.marker_lifetime": base}))
    got = [_lifetime(stage.process(_box_scene(round(s * 1e9)))[0]) for s in stamps_s]
    assert got == pytest.approx(expected, abs=1e-6)


def test_a_stamp_with_a_second_or_more_of_nanoseconds_is_malformed():
    """builtin_interfaces/Time keeps nanosec below 1e9; one at 2^31 - 1 s plus 1.5e9 ns
    gave outputs stamped -2 147 483 645 s."""
    from lidar_obstacles.errors import CloudFormatError

    msg = _box_scene(0)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 2**31 - 1, 1_500_000_000
    with pytest.raises(CloudFormatError, match="nanosec 1500000000, not below 1e9"):
        DetectorStage(ObstacleDetectorConfig()).process(msg)


def test_output_clouds_are_aligned_with_zeros_between_fields():
    """Every FLOAT32 of `ground`, `obstacles` and `dem` starts at a multiple of 4 and
    every point too (C++ readers map a point to a struct: `height_above_ground` at offset
    17 and a 13-byte DEM point were read unaligned); the padding is zeros, so a replay
    writes the same bytes every time."""
    from lidar_obstacles.core.dem import DemGrid

    pts = np.zeros(6, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1")])
    pts["x"] = np.arange(6)
    stage = DetectorStage(ObstacleDetectorConfig())
    job = stage.start(messages.cloud(pts, messages.header(1, "map")))
    outputs = dict((name, msg) for name, msg in stage.finish(job)[0]
                   if name in ("ground", "obstacles"))
    grid = DemGrid(np.arange(6, dtype=np.float32).reshape(2, 3), np.zeros((2, 3), np.uint8),
                   np.ones((2, 3), np.uint32), np.zeros(2), 1.0)
    outputs["dem"] = messages.dem_messages(grid, messages.header(1, "map"))[0]
    for name, msg in outputs.items():
        offsets = {f.name: f.offset for f in msg.fields}
        assert msg.point_step % 4 == 0, name
        assert all(offsets[f.name] % 4 == 0 for f in msg.fields if f.datatype == 7), name
        used = sum(1 if f.datatype in (1, 2) else 4 for f in msg.fields)
        if msg.width * msg.height:
            raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, msg.point_step)
            spans = np.zeros(msg.point_step, bool)
            for f in msg.fields:
                spans[f.offset:f.offset + (1 if f.datatype in (1, 2) else 4)] = True
            assert used < msg.point_step and not raw[:, ~spans].any(), name


def test_a_dem_from_the_detectors_ground_topic_is_the_dem_it_would_find():
    """`dem.ground_source: input` takes obstacle_detector's `ground` (remapped to its
    `points`) and does not filter the cloud again: the same DEM as `detector` on the raw
    clouds, at a fraction of the cost. A cloud without height_above_ground is refused (a
    raw cloud would put every crown and roof into the DEM); of one with obstacles in it,
    only the ground (class 2) is taken."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.core.simulate import SimSettings, simulate_flight
    from lidar_obstacles.errors import CloudFormatError
    from lidar_obstacles.ros.stages import DemStage

    detector = DetectorStage(ObstacleDetectorConfig())
    own = DemStage(DemBuilderConfig())
    taken = DemStage(replace(DemBuilderConfig(), {"dem.ground_source": "input"}))
    mixed = DemStage(replace(DemBuilderConfig(), {"dem.ground_source": "input"}))
    for frame in simulate_flight(SimSettings(scene="mixed", seed=2, duration=0.5)):
        msg = messages.cloud(frame.points, messages.header(int(frame.stamp * 1e9) + 1, "map"))
        own.process(msg)
        outputs = dict(detector.finish(detector.start(msg))[0])
        taken.process(outputs["ground"])
        both = np.concatenate([read_points(outputs["ground"]), read_points(outputs["obstacles"])])
        mixed.process(messages.cloud(both, messages.header(int(frame.stamp * 1e9) + 1, "map")))
    a, b, c = own.grid(), taken.grid(), mixed.grid()
    assert a.elevation.size > 100
    assert np.array_equal(a.elevation, b.elevation, equal_nan=True)
    assert np.array_equal(a.elevation, c.elevation, equal_nan=True)
    with pytest.raises(CloudFormatError, match="no height_above_ground field"):
        taken.process(msg)
    assert taken.shares_ground_with(ObstacleDetectorConfig(tiling=replace(
        ObstacleDetectorConfig().tiling, {"size": 33.0})))


def _terrain(stamp_s: float, frame: str = "map", hill: float = 0.0, x0: float = 0.0,
             z0: float = 0.0, seed: int = 0):
    """A 60 x 60 m cloud of bare ground (20 000 points) from x0, with a smooth hill of
    `hill` m in its middle, stamped stamp_s s in `frame`."""
    rng = np.random.default_rng(seed)
    points = np.zeros(20000, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    x, y = rng.uniform(0, 60, 20000), rng.uniform(0, 60, 20000)
    r2 = (x - 30) ** 2 + (y - 30) ** 2
    points["x"], points["y"] = x + x0, y
    points["z"] = z0 + hill * np.exp(-r2 / 300.0) + rng.normal(0, 0.02, 20000)
    return messages.cloud(points, messages.header(int(stamp_s * 1e9), frame))


def test_a_clock_gone_back_or_a_new_frame_starts_afresh():
    """Clouds stamped before the newest (a simulator reset, a bag played again or an
    older one) kept the ground context, stamped "later", for good: a 6 m hill after a flat
    field over the same ground kept ~22 % of its ground as obstacles, cloud after cloud.
    Now such a cloud, or one in another frame, starts afresh: as a new node would."""
    from lidar_obstacles.core.pipeline import RESTART_AFTER_S

    stage = DetectorStage(ObstacleDetectorConfig())
    said = [stage.process(_terrain(1000.0 + k, seed=k))[1]["restart"] for k in range(3)]
    fresh = DetectorStage(ObstacleDetectorConfig())
    for k in range(4):
        msg = _terrain(500.0 + k, hill=6.0, seed=10 + k)
        _, stats = stage.process(msg)
        said.append(stats["restart"])
        _, alone = fresh.process(msg)
        assert stats["ground"] == alone["ground"] == 20000, (k, stats["ground"])
    assert said[:3] == ["", "", ""] and said[4:] == ["", "", ""]
    assert said[3] == "a cloud stamped 502.000 s before the newest (the clock went back)"
    # a late cloud (reordered by a second at most) goes on with the stream
    assert stage.process(_terrain(503.0 - RESTART_AFTER_S + 0.1, hill=6.0))[1]["restart"] == ""
    # a new frame starts afresh too
    _, stats = stage.process(_terrain(504.0, frame="odom", hill=6.0))
    assert stats["restart"] == "a cloud in frame 'odom' after clouds in 'map'"


def test_the_dem_starts_afresh_in_a_new_frame():
    """A cloud in `odom` at z 0 and one in `map` at z 20 went into one DEM, published as
    `map`'s: half its cells were another frame's."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.ros.stages import DemStage

    stage, fresh = DemStage(DemBuilderConfig()), DemStage(DemBuilderConfig())
    assert stage.process(_terrain(1.0, frame="odom"))["restart"] == ""
    second = _terrain(2.0, frame="map", x0=50.0, z0=20.0)
    assert stage.process(second)["restart"] == "a cloud in frame 'map' after clouds in 'odom'"
    fresh.process(second)
    grid = stage.grid()
    assert stage.frame_id == "map" and np.nanmin(grid.elevation) > 19.0
    # (as a new stage's, but for which points the thinning held out: its random stream goes on)
    assert abs(np.isfinite(grid.elevation).sum() - np.isfinite(fresh.grid().elevation).sum()) < 50


def _far_off(stamp_s: float, frame: str = "map"):
    """A cloud the detector and the DEM refuse: it lies 1e9 m from the frame's origin."""
    points = np.zeros(100, [("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    points["x"] = 1e9 + np.arange(100.0)
    return messages.cloud(points, messages.header(int(stamp_s * 1e9), frame))


@pytest.mark.parametrize("bad_stamp, bad_frame", [(0.0, "map"), (11.0, "odom")])
def test_a_refused_cloud_changes_nothing_of_the_stream(bad_stamp, bad_frame):
    """A refused cloud stamped 0 or in another frame had started the stream over before
    it was refused: the DEM lost every cell but the next cloud's, without a word or a
    count (`restarts` 0), and a new frame's cloud made the next good one start over. The
    stages that saw it end as their twins that did not."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.errors import CloudFormatError
    from lidar_obstacles.ros.stages import DemStage

    good = [_terrain(10.0, seed=0), _terrain(11.0, x0=70.0, seed=1)]  # the west, the east
    last = _terrain(12.0, seed=5)
    stages = DetectorStage(ObstacleDetectorConfig()), DemStage(DemBuilderConfig())
    twins = DetectorStage(ObstacleDetectorConfig()), DemStage(DemBuilderConfig())
    for msg in good:
        for stage in (*stages, *twins):
            stage.process(msg)
    for stage in stages:
        with pytest.raises(CloudFormatError, match="1e"):
            stage.process(_far_off(bad_stamp, bad_frame))
    (out, stats), (twin_out, _) = stages[0].process(last), twins[0].process(last)
    assert stats["restart"] == "" and stages[0].pipeline.timeline.restarts == 0
    assert read_points(dict(out)["ground"]).tobytes() == \
        read_points(dict(twin_out)["ground"]).tobytes()
    # the DEM published meanwhile keeps its frame and time (dem_outputs' header)
    assert (stages[1].frame_id, stages[1].last_stamp_ns) == ("map", 11 * 10**9)
    assert stages[1].process(last)["restart"] == ""
    twins[1].process(last)
    assert np.array_equal(stages[1].grid().elevation, twins[1].grid().elevation,
                          equal_nan=True)


def test_the_span_export_dem_names_is_of_the_points_its_dem_would_take():
    """Over dem.max_cells, the whole survey's span is said: of the points the DEM takes, not
    of a stray point 5 km off (the span said 5000 x 5000 m for 130 x 60 m of ground) nor
    of a cloud refused."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.errors import CloudFormatError
    from lidar_obstacles.ros.stages import DemStage

    stage = DemStage(replace(DemBuilderConfig(), {"dem.max_cells": 2000, "dem.extent": 0.0}),
                     whole=True)
    for k in range(3):  # 0-130 x 0-60 m of ground, and one stray point 5 km off
        msg = _terrain(10.0 + k, x0=35.0 * k, seed=k)
        points = read_points(msg).copy()
        points[0] = (5000.0, 5000.0, 0.0)
        stage.process(messages.cloud(points, msg.header))
    with pytest.raises(CloudFormatError):
        stage.process(_far_off(13.0))
    assert stage.too_large
    assert stage.too_large_message().startswith("the survey spans 130 x 60 m: ")


def test_a_frame_named_with_a_leading_slash_is_the_same_frame():
    """`/map` after `map` started the stream over, cloud after cloud (tf2 reads them as one
    frame), and a cloud in `/odom` with odometry in `odom` was moved by the pose twice."""
    from lidar_obstacles.ros.stages import Pose

    stage = DetectorStage(ObstacleDetectorConfig())
    said = [stage.process(_terrain(10.0 + k, frame=f))[1]["restart"]
            for k, f in enumerate(("map", "/map", "map", "/map"))]
    assert said == ["", "", "", ""]
    moved = DetectorStage(replace(ObstacleDetectorConfig(), {"use_odometry": True}))
    pose = Pose(10 * 10**9, np.array([100.0, 0.0, 50.0]), np.array([0.0, 0.0, 0.0, 1.0]),
                "odom", "base_link")
    for cloud_frame, pose_frame in (("/odom", "odom"), ("odom", "/odom")):
        pose = Pose(pose.stamp_ns, pose.position, pose.orientation, pose_frame, "base_link")
        out, _ = moved.process(_terrain(10.0, frame=cloud_frame), pose)
        ground = read_points(dict(out)["ground"])
        assert abs(float(np.mean(ground["x"])) - 30.0) < 2.0, (cloud_frame, pose_frame)


def test_a_pose_in_another_frame_does_not_place_the_grids():
    """Odometry in `odom` at (500, 500), clouds in `map` round (30, 30), use_odometry off:
    the clearance grid stood round (500, 500) with nothing known, and the DEM's window
    too (0 of its cells). The pose places them only in its own frame."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.ros.stages import DemStage, Pose

    far = Pose(0, np.array([500.0, 500.0, 60.0]), np.array([0.0, 0.0, 0.0, 1.0]), "odom",
               "base_link")
    msg = _terrain(1.0)
    out, _ = DetectorStage(ObstacleDetectorConfig()).process(msg, far)
    grid = dict(out)["clearance"]
    assert abs(grid.info.origin.position.x - 30.0) < 60.0
    assert (np.array(grid.data) >= 0).sum() > 1000
    dem = DemStage(DemBuilderConfig())
    dem.process(msg, far)
    assert np.isfinite(dem.grid().elevation).sum() > 1000
    # in the pose's own frame the grid is centred on it, as before
    near = Pose(0, np.array([10.0, 10.0, 60.0]), np.array([0.0, 0.0, 0.0, 1.0]), "map")
    out, _ = DetectorStage(ObstacleDetectorConfig()).process(msg, near)
    size = ObstacleDetectorConfig().clearance.size
    assert abs(dict(out)["clearance"].info.origin.position.x - (10.0 - size / 2)) <= 1.0


def test_an_empty_cloud_publishes_an_unknown_clearance_grid():
    """No return (high over ground, over water): the markers were cleared but the last
    clearance grid, obstacles and all, stood until the next cloud with points."""
    stage = DetectorStage(ObstacleDetectorConfig())
    first = dict(stage.process(_terrain(1.0, hill=6.0))[0])["clearance"]
    empty = np.zeros(0, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    out = dict(stage.process(messages.cloud(empty, messages.header(int(1.1e9), "map")))[0])
    grid = out["clearance"]
    assert set(grid.data) == {-1} and len(grid.data) == len(first.data)
    assert grid.info.origin == first.info.origin and grid.header.stamp.nanosec == 100_000_000
    assert [m.action for m in out["obstacle_markers"].markers] == [3]  # DELETEALL


def test_a_dem_float32_cannot_hold_is_said():
    """The `dem` cloud's x y are FLOAT32 (the contract's): at a UTM northing of 5.7e6 m
    they hold 0.5 m, and 0.25 m cells fell two to a value without a word."""
    from lidar_obstacles.core.dem import DemGrid
    from lidar_obstacles.ros.stages import coarse_dem_warning

    def grid(origin, res):
        return DemGrid(np.zeros((800, 10), np.float32), np.zeros((800, 10), np.uint8),
                       np.ones((800, 10), np.uint32), np.array(origin), res)

    said = coarse_dem_warning(grid([500000.0, 5700000.0], 0.25))
    assert said is not None and "hold a position only to 0.5 m" in said
    assert coarse_dem_warning(grid([500000.0, 5700000.0], 2.0)) is None
    assert coarse_dem_warning(grid([-100.0, -100.0], 0.05)) is None


def test_a_late_odometry_pose_goes_in_its_place():
    """One pose 50 ms older than the last (best-effort odometry reordered, two publishers)
    emptied the buffer: the clouds before it waited for poses or were dropped. A clock
    gone back by more than a second still starts it over."""
    from lidar_obstacles.ros.node_base import PoseBuffer
    from lidar_obstacles.ros.stages import Pose

    def at(s: float) -> Pose:
        return Pose(int(s * 1e9), np.array([s, 0.0, 50.0]), np.array([0.0, 0.0, 0.0, 1.0]),
                    "map")

    poses = PoseBuffer()
    for s in (10.0, 10.1, 10.2, 10.15):
        poses.add(at(s))
    assert [poses.nearest(int(s * 1e9), 0.01).position[0] for s in (10.0, 10.1, 10.15, 10.2)] \
        == [10.0, 10.1, 10.15, 10.2]
    for s in (3.0, 3.02, 3.04):  # (CLOCK_JUMP_POSES in a row)
        poses.add(at(s))
    assert poses.nearest(int(10.2e9), 0.01) is None
    assert poses.nearest(int(3.02e9), 0.01).position[0] == 3.02
    for s in (6.0, 6.02, 6.04):  # odometry back after a 3 s gap: it goes on from there
        poses.add(at(s))
    assert [poses.nearest(int(s * 1e9), 0.01).position[0] for s in (3.0, 6.0, 6.04)] \
        == [3.0, 6.0, 6.04]


@pytest.mark.parametrize("glitch", [2.0, 1000.0])
def test_one_odometry_pose_of_another_clock_empties_nothing(glitch):
    """One pose stamped seconds back (a glitch; an unset stamp is refused outright) or far
    ahead emptied the poses held, and the clouds waiting for them were dropped; now the
    clock is taken to have gone back only when CLOCK_JUMP_POSES poses in a row say so,
    and a pose far ahead ages nothing out."""
    from lidar_obstacles.ros.node_base import CLOCK_JUMP_POSES, PoseBuffer
    from lidar_obstacles.ros.stages import Pose

    def at(s: float) -> Pose:
        return Pose(int(s * 1e9), np.array([s, 0.0, 50.0]), np.array([0.0, 0.0, 0.0, 1.0]),
                    "map")

    poses = PoseBuffer()
    for s in (10.0, 10.02, 10.04, glitch, *(10.06 + 0.02 * k for k in range(CLOCK_JUMP_POSES))):
        assert poses.add(at(s)) is None
    for s in (10.0, 10.04, 10.06, 10.06 + 0.02 * (CLOCK_JUMP_POSES - 1)):
        assert poses.nearest(int(s * 1e9), 0.001).position[0] == pytest.approx(s), s
    assert poses.nearest(int(glitch * 1e9), 0.5) is None
    assert "unset stamp" in poses.add(at(0.0))


def test_a_subscription_destroyed_while_the_wait_set_is_built_does_not_stop_the_node():
    """`input.reliability: auto` swaps the input subscription from a timer on another of
    a multi-threaded executor's threads; rclpy then raised InvalidHandle from the wait set
    being built, in the spin loop, and dem_builder died (exit 1). The loop goes on."""
    from rclpy._rclpy_pybind11 import InvalidHandle

    from lidar_obstacles.ros.node_base import spin_until

    class Executor:
        spins = 0

        def spin_once(self) -> None:
            self.spins += 1
            if self.spins == 2:
                raise InvalidHandle("cannot use Destroyable because destruction was requested")

    executor = Executor()
    spin_until(executor, lambda: executor.spins >= 5)
    assert executor.spins == 5
