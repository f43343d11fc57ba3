"""The contract's outputs (../shared/design/interfaces.md, Topics): what `replay` writes for
the topics the nodes publish (obstacle_edges, the DEM, the markers), vegetation by height,
and of the running nodes their input and output QoS and their parameter descriptors."""
from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from nav_msgs.msg import MapMetaData  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rcl_interfaces.srv import DescribeParameters, GetParameters  # noqa: E402
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,  # noqa: E402
                       ReliabilityPolicy)
from sensor_msgs.msg import Image, PointCloud2  # noqa: E402

from lidar_obstacles.config import NODE_CONFIGS, ObstacleDetectorConfig, params_of  # noqa: E402
from lidar_obstacles.core.classes import CLASS_NAMES, vegetation_class  # noqa: E402
from lidar_obstacles.core.obstacles import classify_obstacles  # noqa: E402
from lidar_obstacles.io.bags import BagReader  # noqa: E402
from lidar_obstacles.io.pointcloud2 import read_points  # noqa: E402
from lidar_obstacles.ros import messages  # noqa: E402
from test_live_nodes import _call, _spin_until, _stop  # noqa: E402
from test_live_nodes import _start as start_node  # noqa: E402

NS = "/contract_outputs"


# ------------------------------------------------------------------ a replay's outputs


@pytest.fixture(scope="module")
def replayed(tmp_path_factory) -> dict[str, list]:
    """Every message of a replay of a short simulated flight with `features.enabled`, by
    topic (small clouds: the feature points cost time per cloud)."""
    from lidar_obstacles.ros import offline

    tmp = tmp_path_factory.mktemp("replayed")
    params = tmp / "features.yaml"
    params.write_text("/**:\n  ros__parameters:\n    features.enabled: true\n")
    offline.simulate(tmp / "flight", scene="mixed", seed=7, duration=1.0, frame="map",
                     points_per_frame=15000)
    summary = offline.replay(tmp / "flight", tmp / "out", params_file=params)
    assert summary["messages"] == 10 and summary["rejected"] == 0
    out: dict[str, list] = {}
    with BagReader(tmp / "out") as reader:
        for rec in reader.records():
            out.setdefault(rec.topic, []).append(reader.deserialize(rec))
    return out


def _layout(msg) -> list[tuple]:
    return [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]


def test_obstacle_edges_are_obstacle_points_with_the_obstacles_fields(replayed):
    edges, obstacles = replayed["/obstacle_edges"], replayed["/obstacles"]
    assert len(edges) == len(obstacles) == 10
    names = [f[0] for f in _layout(obstacles[0])]
    assert "class" in names and "height_above_ground" in names
    total = 0
    for e, o in zip(edges, obstacles):
        assert _layout(e) == _layout(o)
        assert (e.header.stamp.sec, e.header.stamp.nanosec, e.header.frame_id) == \
            (o.header.stamp.sec, o.header.stamp.nanosec, o.header.frame_id)
        ep, op = read_points(e).reshape(-1), read_points(o).reshape(-1)
        total += len(ep)
        # each feature point is one of this cloud's obstacle points, all fields alike
        # (the simulator's point_id names a point)
        assert len(ep) < len(op)
        assert len(np.unique(ep["point_id"])) == len(ep)
        same = op[np.isin(op["point_id"], ep["point_id"])]
        assert len(same) == len(ep)
        same, ep = same[np.argsort(same["point_id"])], ep[np.argsort(ep["point_id"])]
        for name in names:
            assert same[name].tobytes() == ep[name].tobytes(), name
        assert not np.isin(ep["class"], (2, 7)).any()  # not ground, not noise
    assert total > 100, total


def test_dem_is_an_organized_cloud_its_image_and_info_the_same_grid(replayed):
    (dem,), (image,), (info,) = replayed["/dem"], replayed["/dem_image"], replayed["/dem_info"]
    assert dem.height > 1 and dem.width > 1  # organized: rows x cols
    fields = {f.name: (f.datatype, f.count) for f in dem.fields}
    assert fields == {"x": (7, 1), "y": (7, 1), "z": (7, 1), "interpolated": (2, 1)}
    pts = read_points(dem, keep_non_finite=True)
    assert pts.shape == (dem.height, dem.width)
    unknown = np.isnan(pts["z"])
    # the rolling grid reaches beyond the flight: unknown cells, and filled ones
    assert 0 < unknown.sum() < unknown.size, unknown.sum()
    assert (pts["interpolated"][unknown] == 0).all()
    assert set(np.unique(pts["interpolated"])) == {0, 1}
    assert np.isfinite(pts["z"][pts["interpolated"] == 1]).all()
    # the image: 32FC1, the same elevations, NaN where unknown
    assert (image.encoding, image.height, image.width) == ("32FC1", dem.height, dem.width)
    assert image.step == 4 * image.width and image.is_bigendian == 0
    assert bytes(image.data) == np.ascontiguousarray(pts["z"], "<f4").tobytes()
    # the info: the resolution and origin of that grid (cell centres at origin + half a cell)
    assert (info.width, info.height) == (dem.width, dem.height) and info.resolution > 0
    res, ox, oy = info.resolution, info.origin.position.x, info.origin.position.y
    cols, rows = np.arange(dem.width), np.arange(dem.height)
    np.testing.assert_allclose(pts["x"][0], ox + (cols + 0.5) * res, atol=1e-3)
    np.testing.assert_allclose(pts["y"][:, 0], oy + (rows + 0.5) * res, atol=1e-3)


def test_markers_are_named_and_coloured_by_class_with_a_label_per_object(replayed):
    CUBE, TEXT, ADD = 1, 9, 0  # visualization_msgs/Marker
    colours: dict[str, set] = {}
    boxes = 0
    for array in replayed["/obstacle_markers"]:
        added = [m for m in array.markers if m.action == ADD]
        cubes = {(m.ns, m.id): m for m in added if m.type == CUBE}
        texts = {(m.ns, m.id): m for m in added if m.type == TEXT}
        assert len(cubes) + len(texts) == len(added)
        # one label per box, in its namespace, naming its class and clearance
        assert {(ns, i + 1) for ns, i in cubes} == set(texts)
        for (ns, _), m in cubes.items():
            assert ns in set(CLASS_NAMES.values()) - {"ground", "noise"}, ns
            colours.setdefault(ns, set()).add((m.color.r, m.color.g, m.color.b))
        for (ns, _), m in texts.items():
            assert m.text.startswith(f"{ns} ") and "clearance" in m.text, m.text
        boxes += len(cubes)
    assert boxes > 10
    # the flight shows several classes; each has one colour, and no two share one
    assert len(colours) >= 2, colours
    assert all(len(c) == 1 for c in colours.values()), colours
    assert len({c for cs in colours.values() for c in cs}) == len(colours), colours


# ------------------------------------------------------------------ vegetation by height


def test_vegetation_is_low_medium_or_high_by_height_above_ground():
    # the contract's bands: 3 below 0.5 m, 4 from 0.5 to 2 m, 5 above 2 m
    assert vegetation_class(np.array([0.0, 0.3, 0.4999, 0.5, 1.0, 2.0, 2.001, 5.0])).tolist() \
        == [3, 3, 3, 4, 4, 4, 5, 5]
    # a bush grown into a tree on flat ground: a rough mass of points from 0.1 to 6 m
    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-20, 20, (8000, 2)), rng.normal(0, 0.02, 8000)])
    n = 3000
    radius, angle = 2.5 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    crown = np.column_stack([radius * np.cos(angle), radius * np.sin(angle),
                             rng.uniform(0.1, 6.0, n)])
    probes = np.array([[0.3, 0.2, 0.3], [0.2, -0.3, 1.0], [-0.4, 0.1, 5.0]])
    xyz = np.concatenate([ground, crown, probes])
    is_ground = np.arange(len(xyz)) < len(ground)
    hag = np.where(is_ground, 0.0, xyz[:, 2]).astype(np.float32)
    res = classify_obstacles(xyz, is_ground, hag, cfg=ObstacleDetectorConfig().obstacles)
    assert res.classes[-3:].tolist() == [3, 4, 5]
    tree = res.classes[len(ground):]
    h = xyz[len(ground):, 2]
    assert (tree[h < 0.5] == 3).all()
    assert (tree[(h >= 0.5) & (h <= 2.0)] == 4).all()
    assert (tree[h > 2.0] == 5).all()


# ------------------------------------------------------------------ the running nodes

DETECTOR_OUT = ("ground", "obstacles", "obstacle_markers", "clearance", "obstacle_edges")
DEM_OUT = ("dem", "dem_image", "dem_info")


def _start(node: str, *ros_args: str) -> subprocess.Popen:
    return start_node(f"lidar_obstacles.scripts.{node}", *ros_args, ns=NS)


@pytest.fixture(scope="module")
def nodes():
    """A probe node, and the detector (`input.reliability: auto`, the default) and the DEM
    builder (forced best effort) running in NS, both taking NS/points."""
    det = _start("obstacle_detector", "-p", "features.enabled:=true")
    dem = _start("dem_builder", "-p", "input.reliability:=best_effort",
                 "-p", "dem.publish_rate:=4.0")
    rclpy.init()
    probe = rclpy.create_node("contract_outputs_probe")
    try:
        up = _spin_until(probe, lambda: all(
            probe.count_publishers(f"{NS}/{t}") for t in DETECTOR_OUT + DEM_OUT), 60)
        assert up, (det.poll(), dem.poll())
        yield probe
    finally:
        probe.destroy_node()
        rclpy.try_shutdown()
        results = {"obstacle_detector": _stop(det), "dem_builder": _stop(dem)}
    for name, (code, log) in results.items():
        assert code == 0, (name, log[-3000:])


def _scene(stamp_ns: int) -> PointCloud2:
    """Flat ground 40 m x 32 m with a 5 m box on it."""
    points = np.zeros((40, 50), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    points["x"], points["y"] = np.meshgrid(np.arange(50) * 0.8, np.arange(40) * 0.8)
    points["z"][10:16, 20:26] += 5.0
    return messages.cloud(points.ravel(), messages.header(stamp_ns, "map"))


def _input_reliability(probe) -> dict[str, ReliabilityPolicy]:
    return {i.node_name: i.qos_profile.reliability
            for i in probe.get_subscriptions_info_by_topic(f"{NS}/points")}


def _stamp_ns(msg) -> int:
    return _ns(msg.header.stamp)


def _ns(stamp) -> int:
    return stamp.sec * 10**9 + stamp.nanosec


def test_best_effort_clouds_are_taken_by_auto_and_by_forced_best_effort(nodes):
    probe = nodes
    reliable = probe.create_publisher(PointCloud2, f"{NS}/points", QoSProfile(
        depth=5, reliability=ReliabilityPolicy.RELIABLE))
    # every publisher reliable: `auto` subscribes reliable, `best_effort` stays so
    assert _spin_until(probe, lambda: _input_reliability(probe) == {
        "obstacle_detector": ReliabilityPolicy.RELIABLE,
        "dem_builder": ReliabilityPolicy.BEST_EFFORT}, 30), _input_reliability(probe)
    probe.destroy_publisher(reliable)
    # a driver publishing best effort alone: `auto` turns best effort
    pub = probe.create_publisher(PointCloud2, f"{NS}/points", QoSProfile(
        depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
    got: dict[str, list] = {"obstacles": [], "dem": []}
    subs = [probe.create_subscription(PointCloud2, f"{NS}/obstacles", got["obstacles"].append,
                                      QoSProfile(depth=10,
                                                 reliability=ReliabilityPolicy.RELIABLE)),
            probe.create_subscription(PointCloud2, f"{NS}/dem", got["dem"].append, QoSProfile(
                depth=1, reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL))]
    try:
        assert _spin_until(probe, lambda: set(_input_reliability(probe).values()) == {
            ReliabilityPolicy.BEST_EFFORT}, 30), _input_reliability(probe)
        first = 100 * 10**9  # this phase's stamps
        sent = [0]

        def both_processed() -> bool:
            pub.publish(_scene(first + sent[0] * 10**8))
            sent[0] += 1
            rclpy.spin_once(probe, timeout_sec=0.2)
            return (any(_stamp_ns(m) >= first for m in got["obstacles"])
                    and any(_stamp_ns(m) >= first for m in got["dem"]))

        assert _spin_until(probe, both_processed, 40), (sent, len(got["obstacles"]),
                                                        len(got["dem"]))
        box = read_points(next(m for m in got["obstacles"] if _stamp_ns(m) >= first))
        assert (box["height_above_ground"] > 4.0).sum() >= 30
    finally:
        for s in subs:
            probe.destroy_subscription(s)
        probe.destroy_publisher(pub)


def test_the_dem_topics_reach_a_late_transient_local_subscriber(nodes):
    probe = nodes
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    types = {"dem": PointCloud2, "dem_image": Image, "dem_info": MapMetaData}
    early: list = []
    sub = probe.create_subscription(MapMetaData, f"{NS}/dem_info", early.append, latched)
    pub = probe.create_publisher(PointCloud2, f"{NS}/points", QoSProfile(
        depth=5, reliability=ReliabilityPolicy.RELIABLE))
    sent = [0]

    def published() -> bool:
        pub.publish(_scene(200 * 10**9 + sent[0] * 10**8))
        sent[0] += 1
        rclpy.spin_once(probe, timeout_sec=0.2)
        return any(_ns(m.map_load_time) >= 200 * 10**9 for m in early)

    late: dict[str, list] = {t: [] for t in types}
    subs = []
    try:
        assert _spin_until(probe, published, 40), sent
        # no more clouds: once the DEM has not changed for 1.5 s (published at 4 Hz), nothing
        # new comes
        last = [len(early), time.monotonic()]

        def quiet() -> bool:
            if len(early) != last[0]:
                last[:] = [len(early), time.monotonic()]
            return time.monotonic() - last[1] > 1.5
        assert _spin_until(probe, quiet, 20)
        before = len(early)
        subs = [probe.create_subscription(types[t], f"{NS}/{t}", late[t].append, latched)
                for t in types]
        assert _spin_until(probe, lambda: all(late.values()), 10), {
            t: len(v) for t, v in late.items()}
        assert len(early) == before  # what the late ones got was kept for them, not new
        assert {t: len(v) for t, v in late.items()} == {t: 1 for t in types}
        assert late["dem_info"][0].width == late["dem"][0].width > 0
        assert bytes(late["dem_image"][0].data) == np.ascontiguousarray(
            read_points(late["dem"][0], keep_non_finite=True)["z"], "<f4").tobytes()
    finally:
        for s in [sub, *subs]:
            probe.destroy_subscription(s)
        probe.destroy_publisher(pub)


def _qos_parameters(probe, node: str, topics) -> dict[str, dict[str, object]]:
    """Each output's history and depth as the node declares them (the middleware's endpoint
    info does not carry them): the read-only `qos_overrides.<topic>.publisher.*`."""
    names = [f"qos_overrides.{NS}/{t}.publisher.{k}" for t in topics for k in ("history", "depth")]
    got = _call(probe, GetParameters, f"{NS}/{node}/get_parameters",
                GetParameters.Request(names=names))
    values = [v.string_value if v.type == ParameterType.PARAMETER_STRING else v.integer_value
              for v in got.values]
    out: dict[str, dict[str, object]] = {}
    for name, value in zip(names, values):
        topic, key = name.split(f"{NS}/")[1].split(".publisher.")
        out.setdefault(topic, {})[key] = value
    return out


def test_outputs_are_reliable_keep_last_small_depth_and_the_dem_transient_local(nodes):
    probe = nodes
    for node, topics in (("obstacle_detector", DETECTOR_OUT), ("dem_builder", DEM_OUT)):
        for topic in topics:
            infos = [i for i in probe.get_publishers_info_by_topic(f"{NS}/{topic}")
                     if i.node_name == node]
            assert len(infos) == 1, (topic, infos)
            qos = infos[0].qos_profile
            assert qos.reliability == ReliabilityPolicy.RELIABLE, (topic, qos)
            durability = (DurabilityPolicy.TRANSIENT_LOCAL if topic in DEM_OUT
                          else DurabilityPolicy.VOLATILE)
            assert qos.durability == durability, (topic, qos)
        declared = _qos_parameters(probe, node, topics)
        for topic in topics:
            assert declared[topic]["history"] == HistoryPolicy.KEEP_LAST.name.lower(), topic
            assert 1 <= declared[topic]["depth"] <= 10, (topic, declared[topic])


def test_parameter_descriptors_give_the_schemas_description_unit_range_and_read_only(nodes):
    probe = nodes
    for node in ("obstacle_detector", "dem_builder"):
        schema = list(params_of(NODE_CONFIGS[node]))
        got = _call(probe, DescribeParameters, f"{NS}/{node}/describe_parameters",
                    DescribeParameters.Request(names=[p.name for p in schema]))
        assert len(got.descriptors) == len(schema)
        numeric = 0
        for info, d in zip(schema, got.descriptors):
            assert d.name == info.name
            assert d.read_only == info.spec.read_only, info.name
            assert d.description.startswith(info.spec.description), info.name
            if info.type not in (int, float):
                continue
            numeric += 1
            assert info.spec.unit and d.description.endswith(f"[{info.spec.unit}]"), (
                info.name, d.description)
            if info.type is float:
                assert d.type == ParameterType.PARAMETER_DOUBLE and not d.integer_range
                assert [(r.from_value, r.to_value) for r in d.floating_point_range] == \
                    [(float(info.spec.min), float(info.spec.max))], info.name
            else:
                assert d.type == ParameterType.PARAMETER_INTEGER and not d.floating_point_range
                assert [(r.from_value, r.to_value) for r in d.integer_range] == \
                    [(int(info.spec.min), int(info.spec.max))], info.name
        assert numeric > 30, (node, numeric)
        # the schema's read-only ones: the input's QoS and depth
        assert {p.name for p, d in zip(schema, got.descriptors) if d.read_only} == {
            "input.reliability", "input.depth"}
