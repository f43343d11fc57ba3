"""The same scene presented differently gives the same answer: the points in another order,
the cloud moved by whole metres (survey coordinates), every point twice."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.config import ObstacleDetectorConfig
from lidar_obstacles.core.ground import classify_ground
from lidar_obstacles.core.pipeline import ObstacleDetector

from conftest import data_file

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


@pytest.mark.parametrize("method", ["tin", "ransac"])
def test_the_other_ground_methods_do_not_depend_on_the_order_of_the_points(method):
    # RANSAC drew its samples by index; the TIN's seeds, facets and Qhull's triangulation
    # of a lattice's cocircular points followed the input's order.
    from lidar_obstacles.config import replace

    cfg = replace(CFG, {"ground.method": method})
    xyz = _quantized(_scene(4, n=3000, size=50.0))
    context = _quantized(_scene(5, n=1000, size=50.0)) + [25.0, 0.0, 0.0]

    def run(points, ctx):
        return classify_ground(points, tiling=cfg.tiling, ground=cfg.ground, tin=cfg.tin,
                               ransac=cfg.ransac, context_xyz=ctx,
                               rng=np.random.default_rng(0))

    first = run(xyz, context)
    order = np.random.default_rng(1).permutation(len(xyz))
    again = run(xyz[order], context[::-1])
    np.testing.assert_array_equal(again.ground, first.ground[order])
    np.testing.assert_array_equal(again.height_above_ground, first.height_above_ground[order])


def _quantized(xyz, step=0.01):
    """Coordinates on a LAS file's 1 cm lattice, as read back from it."""
    return np.round(xyz / step) * step


def test_the_ground_does_not_depend_on_where_the_cloud_lies():
    # Survey coordinates lie on a 1 cm lattice, so points sit exactly at the filter's
    # thresholds and on its cells' edges, and which side they fell on was decided by the
    # binary rounding of the coordinates, which moving the cloud up 2 km or into another
    # binade of UTM changed. (The raster is counted from the cloud's lowest point: a
    # shift by a fraction of a metre moves it with the cloud.)
    xyz = _quantized(_scene(1))
    first = _ground(xyz)
    for shift in ([0.0, 0.0, 2000.0], [300000.0, 3000000.0, 1000.0], [-7000.0, 0.0, 0.0]):
        again = _ground(xyz + shift)
        np.testing.assert_array_equal(again.ground, first.ground)
        np.testing.assert_array_equal(again.height_above_ground, first.height_above_ground)
    # by a fraction of a metre: the same labels, the heights to the rounding of the
    # bilinear weights
    again = _ground(xyz + [0.37, 0.61, 0.0])
    np.testing.assert_array_equal(again.ground, first.ground)
    np.testing.assert_allclose(again.height_above_ground, first.height_above_ground, atol=1e-6)


def _classes(xyz):
    return ObstacleDetector(CFG).process(xyz).classes


def test_a_real_survey_moved_keeps_its_classes():
    # ISPRS samp12 (UTM, 1 cm lattice) moved 2 km up: 60 points changed class before, 46
    # of them their ground label; moved by a fraction of a metre, none (the raster counts
    # from the lowest point), but 7 once the centred coordinates were rounded and a cell's
    # edge was judged without cell_index's slack
    from lidar_obstacles.io.las import read_las

    xyz = read_las(data_file("isprs/samp12-utm.laz")).xyz
    first = _classes(xyz)
    np.testing.assert_array_equal(_classes(xyz + [0.0, 0.0, 2000.0]), first)
    np.testing.assert_array_equal(_classes(xyz + [0.37, 0.61, 0.0]), first)


def test_the_obstacles_voxels_do_not_depend_on_where_the_cloud_lies():
    # Heights on a 1 mm lattice sit on the 0.25 m voxels' edges (counted from the lowest
    # point) one time in 250 in each axis; 1.043 - 0.793 is 0.2499999999999999 in binary,
    # the same heights moved 2 km up 0.25, so such points changed voxel, and their
    # neighbours' shapes with them.
    from lidar_obstacles.core.obstacles import local_shape, voxel_components

    rng = np.random.default_rng(3)
    n = 20000
    xyz = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n),
                           0.793 + rng.uniform(0, 12, n)])
    xyz = _quantized(xyz, 0.001) + [121000.0, 486000.0, 0.0]  # RD metres (AHN)
    first = local_shape(xyz, 2.0)
    labels = voxel_components(xyz, 1.5)
    for shift in ([0.0, 0.0, 2000.0], [500000.0, 5700000.0, 1000.0]):
        again = local_shape(xyz + shift, 2.0)
        for name in ("linearity", "planarity", "roughness", "axis"):
            np.testing.assert_allclose(getattr(again, name), getattr(first, name),
                                       atol=1e-6, err_msg=name)
        np.testing.assert_array_equal(voxel_components(xyz + shift, 1.5), labels)


def test_a_dense_real_survey_moved_2_km_up_keeps_its_classes():
    # AHN4 (1 mm lattice) moved 2 km up: 603 points of a crown became building before
    from lidar_obstacles.io.las import read_las

    xyz = read_las(data_file("ahn4/ahn_2496_9727.laz")).xyz
    np.testing.assert_array_equal(_classes(xyz + [0.0, 0.0, 2000.0]), _classes(xyz))


def test_a_cloud_moved_into_a_utm_odometry_frame_is_classified_at_its_exact_positions():
    # A sensor-frame cloud with FLOAT32 x y z moved by a UTM pose: FLOAT32 holds its
    # northing (5.7e6 m) only in 0.5 m steps. The points are classified, and `evaluate`
    # places them, at their float64 positions whatever the published fields' type (they
    # were 0.1-0.2 m off in y when read back from the fields); `odometry_xyz_type:
    # float64` publishes them exactly, the default keeps the input's layout and says so.
    from lidar_obstacles.config import ObstacleDetectorConfig, replace
    from lidar_obstacles.evaluate import _from_points
    from lidar_obstacles.ros import messages
    from lidar_obstacles.ros.stages import Pose, coarse_xyz_warning, prepare

    pts = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                             ("intensity", "<f4"), ("classification", "u1")])
    pts["x"], pts["y"], pts["z"] = [0.1, 1.23, -3.37], [0.2, 2.0, 5.55], [-40.0, -38.2, -41.07]
    pts["classification"] = [2, 5, 6]
    msg = messages.cloud(pts, messages.header(10**9, "lidar"))
    pose = Pose(10**9, np.array([512345.678, 5712345.678, 345.6]),
                np.array([0.0, 0.0, 0.3826834, 0.9238795]), "utm")
    expected = (np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(np.float64)
                @ pose.rotation().T + pose.position)
    for widen in (False, True):
        prep = prepare(msg, keep_non_finite=False, max_points=100, pose=pose, transform=True,
                       widen_xyz=widen)
        np.testing.assert_array_equal(prep.xyz, expected)
        np.testing.assert_array_equal(_from_points(prep.points, 1.0, prep.xyz).xyz, expected)
        assert prep.points["classification"].tolist() == [2, 5, 6] and prep.frame_id == "utm"
        assert (prep.points.dtype["y"] == np.float64) == widen
        published = np.column_stack([prep.points[a] for a in "xyz"]).astype(float)
        assert (np.abs(published - expected).max() < 1e-9) == widen
    cfg = replace(ObstacleDetectorConfig(), {"use_odometry": True})
    said = coarse_xyz_warning(msg, pose, cfg)
    assert said is not None and "0.5 m" in said and "odometry_xyz_type" in said
    assert coarse_xyz_warning(msg, pose, replace(cfg, {"odometry_xyz_type": "float64"})) is None
    near = Pose(10**9, np.array([3512.3, -812.5, 345.6]), pose.orientation, "odom")
    assert coarse_xyz_warning(msg, near, cfg) is None  # a local frame: FLOAT32 to 0.5 mm
    # clouds already in the odometry's frame are not moved, `/utm` being `utm` (tf2's
    # names): nothing to say of their fields
    in_utm = messages.cloud(pts, messages.header(10**9, "/utm"))
    assert coarse_xyz_warning(in_utm, pose, cfg) is None


def _with_noise_and_a_pole(xyz):
    """xyz with a few isolated echoes high above it and a 6 m pole on the ground."""
    rng = np.random.default_rng(7)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    noise = np.column_stack([rng.uniform(lo[0], hi[0], 8), rng.uniform(lo[1], hi[1], 8),
                             np.full(8, hi[2] + 30.0) + rng.uniform(0, 20, 8)])
    foot = np.array([lo[0] + 12.0, lo[1] + 70.0])
    ground_z = xyz[np.argmin(np.hypot(*(xyz[:, :2] - foot).T)), 2]
    z = np.arange(0.2, 6.0, 0.25)
    pole = np.column_stack([np.full(len(z), foot[0]), np.full(len(z), foot[1]), ground_z + z])
    return np.concatenate([xyz, noise, pole])


def test_every_point_twice_gives_every_point_its_class():
    # Counted twice, a point had a neighbour at 0 m (isolated echoes were no longer
    # noise), small objects reached min_points, and the ground's density doubled.
    from lidar_obstacles.config import replace

    xyz = _with_noise_and_a_pole(_scene(2, n=20000))
    cfg = replace(CFG, {"features.enabled": True})
    first = ObstacleDetector(cfg).process(xyz)
    assert (first.classes[20000:20008] == 7).all()  # the isolated echoes are noise
    twice = ObstacleDetector(cfg).process(np.concatenate([xyz, xyz]))
    n = len(xyz)
    for a, b in ((twice.classes[:n], first.classes), (twice.classes[n:], first.classes),
                 (twice.edges[:n], first.edges), (twice.edges[n:], first.edges)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(twice.height_above_ground[n:], first.height_above_ground)
    # a part given twice (overlapping tiles): the same
    some = np.random.default_rng(1).random(n) < 0.3
    again = ObstacleDetector(cfg).process(np.concatenate([xyz, xyz[some]]))
    np.testing.assert_array_equal(again.classes[:n], first.classes)
    np.testing.assert_array_equal(again.classes[n:], first.classes[some])


def test_a_real_survey_given_twice_keeps_its_classes():
    # ISPRS samp54 (Vaihingen, ~2.4 m spacing) with every point twice: 1 185 of its 8 608
    # points changed class (isolated echoes no longer noise: ~520; high vegetation taken
    # for poles: ~650)
    from lidar_obstacles.io.las import read_las

    xyz = read_las(data_file("isprs/samp54-utm.laz")).xyz
    twice = _classes(np.concatenate([xyz, xyz]))
    first = _classes(xyz)
    np.testing.assert_array_equal(twice[:len(xyz)], first)
    np.testing.assert_array_equal(twice[len(xyz):], first)
