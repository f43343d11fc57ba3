"""The offline commands end to end: simulate, las2bag, replay, export-dem, and their errors."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import DATA, REPO, data_file
from lidar_obstacles.cli import main
from lidar_obstacles.errors import CloudFormatError
from lidar_obstacles.io.bags import BagReader
from lidar_obstacles.io.pointcloud2 import read_points
from lidar_obstacles.ros import offline

SHARED_FILES = (sorted(str(p.relative_to(DATA)) for p in DATA.rglob("*.laz"))
                if DATA.is_dir() else [])


def run_cli(*args: str) -> dict:
    """Run the CLI in-process; return its JSON summary."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main([str(a) for a in args])
    assert code == 0, buf.getvalue()
    return json.loads(buf.getvalue())


def cli_subprocess(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidar_obstacles.cli", *map(str, args)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)


def clouds(bag: Path, topic: str) -> list[np.ndarray]:
    with BagReader(bag) as reader:
        return [np.asarray(read_points(reader.deserialize(r), keep_non_finite=True)).reshape(-1)
                for r in reader.records([topic])]


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "flight"
    summary = run_cli("simulate", out, "--duration", "2", "--seed", "3")
    assert summary["messages"] == 20
    return out


def test_bag_timer_is_due_once_a_period_starts_again_when_the_clock_goes_back_and_at_the_end():
    timer = offline._BagTimer(100)
    assert not timer.due(1000)  # the first cloud starts it
    due = [timer.due(t) for t in (1050, 1099, 1100, 1150, 1200)]
    assert due == [False, False, True, False, True]
    assert not timer.due(1250)
    assert not timer.due(500)  # back more than a period: started again, due at 600
    assert not timer.due(599) and timer.due(600)
    assert timer.due(601, end=True)  # the end of the bag: due whatever the time
    assert not offline._BagTimer(100).due(0) and offline._BagTimer(100).due(0, end=True)


def test_simulate_then_replay_keeps_every_point_and_field(sim_bag, tmp_path):
    out = tmp_path / "replayed"
    summary = run_cli("replay", sim_bag, out)
    assert summary["messages"] == 20 and summary["rejected"] == 0
    inputs = clouds(sim_bag, "/points")
    ground, obstacles = clouds(out, "/ground"), clouds(out, "/obstacles")
    assert len(ground) == len(obstacles) == 20
    for src, g, o in zip(inputs, ground, obstacles):
        both = np.concatenate([g, o])
        assert len(both) == len(src)
        # every input field kept byte for byte, two fields added
        assert both.dtype.names == src.dtype.names + ("class", "height_above_ground")
        order = np.argsort(both["point_id"])
        for name in src.dtype.names:
            assert both[name][order].tobytes() == np.sort(src, order="point_id")[name].tobytes()
        assert (g["class"] == 2).all() and (o["class"] != 2).all()
    with BagReader(out) as reader:
        names = {t.topic for t in reader.topics()}
    assert {"/ground", "/obstacles", "/obstacle_markers", "/clearance", "/dem", "/dem_image",
            "/dem_info", "/odom"} <= names


def test_sensor_frame_flight_needs_and_uses_odometry(tmp_path):
    sensor = tmp_path / "sensor"
    made = run_cli("simulate", sensor, "--duration", "1", "--frame", "sensor", "--seed", "3")
    assert (made["frame"], made["frame_id"]) == ("sensor", "lidar")
    params = tmp_path / "odom.yaml"
    params.write_text("/**:\n  ros__parameters:\n    use_odometry: true\n")
    out = tmp_path / "out"
    summary = run_cli("replay", sensor, out, "--params-file", params, "--no-dem")
    assert summary["messages"] == 10
    # without use_odometry it runs in the moving frame, and says so once
    moving = cli_subprocess("replay", sensor, tmp_path / "moving", "--no-dem")
    assert moving.returncode == 0 and moving.stderr.count("use_odometry is false") == 1
    assert "'lidar'" in moving.stderr
    with BagReader(out) as reader:
        rec = next(reader.records(["/obstacles"]))
        assert reader.deserialize(rec).header.frame_id == "map"
    # the moved points keep the input's layout, x y z included, unless widened
    given, moved = clouds(sensor, "/points")[0], clouds(out, "/ground")[0]
    assert given.dtype["x"] == np.float32 and all(
        moved.dtype[a] == given.dtype[a] for a in given.dtype.names)
    wide = tmp_path / "wide.yaml"
    wide.write_text(params.read_text() + "    odometry_xyz_type: float64\n")
    run_cli("replay", sensor, tmp_path / "wide", "--params-file", wide, "--no-dem")
    widened = clouds(tmp_path / "wide", "/ground")[0]
    assert [widened.dtype[a] for a in "xyz"] == [np.float64] * 3
    np.testing.assert_allclose(np.column_stack([widened[a] for a in "xyz"]),
                               np.column_stack([moved[a] for a in "xyz"]), atol=1e-3)
    # The same flight in the map frame gives the same classes.
    mapped = tmp_path / "map"
    run_cli("simulate", mapped, "--duration", "1", "--seed", "3")
    a, b = clouds(out, "/ground")[-1], None
    run_cli("replay", mapped, tmp_path / "out_map", "--no-dem")
    b = clouds(tmp_path / "out_map", "/ground")[-1]
    agree = np.intersect1d(a["point_id"], b["point_id"]).size / max(len(b), 1)
    assert agree > 0.97
    # Clouds already in the odometry's frame pass unchanged with use_odometry (they were
    # moved a second time, by the whole pose).
    run_cli("replay", mapped, tmp_path / "out_map_odom", "--params-file", params, "--no-dem")
    for x, y in zip(clouds(tmp_path / "out_map", "/ground"),
                    clouds(tmp_path / "out_map_odom", "/ground"), strict=True):
        assert x.tobytes() == y.tobytes()


def test_replay_is_deterministic(sim_bag, tmp_path):
    assert run_cli("replay", sim_bag, tmp_path / "a")["topic"] == "/points"
    run_cli("replay", sim_bag, tmp_path / "b")
    a, b = clouds(tmp_path / "a", "/obstacles"), clouds(tmp_path / "b", "/obstacles")
    assert len(a) == len(b) > 0  # zip alone would pass two empty or unequal replays
    assert sum(len(x) for x in a) > 0  # and some obstacle points to compare

    def messages(bag: Path) -> dict[str, list[bytes]]:
        """Every message but /diagnostics (its latencies are the run's), by topic, as
        rosbags serializes it: rclpy's serializer leaves the CDR padding bytes as it finds
        them, so two equal messages may differ there."""
        from lidar_obstacles.io.bags import typestore

        with BagReader(bag) as reader:
            out: dict[str, list[bytes]] = {}
            for rec in reader.records():
                if rec.topic != "/diagnostics":
                    out.setdefault(rec.topic, []).append(bytes(typestore().serialize_cdr(
                        reader.deserialize(rec), rec.msgtype)))
            return out

    got = messages(tmp_path / "a")
    assert {"/ground", "/obstacles", "/obstacle_markers", "/clearance", "/dem"} <= set(got)
    assert got == messages(tmp_path / "b")  # the same bytes, topic by topic, in order


def test_a_replays_output_is_not_taken_for_a_scan(sim_bag, tmp_path):
    """Its /ground and /obstacles have as many messages as the scans had: replaying it
    asks which one is meant, and does it when told."""
    run_cli("replay", sim_bag, tmp_path / "out", "--no-dem")
    res = cli_subprocess("replay", tmp_path / "out", tmp_path / "again", "--no-dem")
    assert res.returncode == 2 and "holds only this package's outputs" in res.stderr
    assert "--topic" in res.stderr and len(res.stderr.splitlines()) == 1
    told = run_cli("replay", tmp_path / "out", tmp_path / "again", "--no-dem",
                   "--topic", "/obstacles")
    assert told["topic"] == "/obstacles" and told["messages"] > 0


def test_replay_copies_other_topics_but_not_other_clouds_or_its_own_outputs(sim_bag, tmp_path):
    """A flight recorded with two LiDARs and the nodes running: the second cloud topic
    crashed the writer (KeyError), and the recorded /ground was written into the new
    /ground beside the replay's own clouds (evaluate then counted each point twice)."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter

    recorded = tmp_path / "recorded"
    with BagReader(sim_bag) as reader, BagWriter(recorded) as bag:
        for topic in ("/points", "/lidar2/points", "/ground"):
            bag.add_topic(topic, POINTCLOUD2)
        bag.add_topic("/odom", "nav_msgs/msg/Odometry")
        for rec in reader.records(["/points", "/odom"]):
            if rec.topic == "/odom":
                bag.write("/odom", rec.stamp_ns, rec.raw)
                continue
            for topic in ("/points", "/lidar2/points", "/ground"):
                bag.write(topic, rec.stamp_ns, rec.raw)
    out = tmp_path / "out"
    summary = run_cli("replay", recorded, out, "--no-dem", "--topic", "/points")
    with BagReader(out) as reader:
        topics = {t.topic: t.count for t in reader.topics()}
    assert topics["/ground"] == topics["/obstacles"] == summary["messages"] == 20
    assert topics["/odom"] == 20 and "/lidar2/points" not in topics
    inputs = sum(len(c) for c in clouds(sim_bag, "/points"))
    assert sum(len(c) for c in clouds(out, "/ground") + clouds(out, "/obstacles")) == inputs


def test_replay_of_stamps_that_go_back_spans_a_positive_time(sim_bag, tmp_path):
    """Clouds stamped in reverse order: bag_seconds -2.0 and a negative real-time factor."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore
    from lidar_obstacles.ros.messages import stamp_ns_of

    backwards = tmp_path / "backwards"
    with BagReader(sim_bag) as reader, BagWriter(backwards) as bag:
        bag.add_topic("/points", POINTCLOUD2)
        records = list(reader.records(["/points"]))
        for rec, later in zip(records, reversed(records)):
            msg = reader.deserialize(rec)
            msg.header.stamp = reader.deserialize(later).header.stamp
            bag.write("/points", rec.stamp_ns,
                      bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    with BagReader(backwards) as reader:
        stamps = [stamp_ns_of(reader.deserialize(r).header) for r in reader.records()]
    assert stamps == sorted(stamps, reverse=True)
    summary = run_cli("replay", backwards, tmp_path / "out", "--no-dem")
    assert summary["bag_seconds"] == 2.0 and summary["real_time_factor"] > 0


def _contents(items) -> list[tuple[str, int, bytes]]:
    """(topic, stamp, CDR) with the padding bytes zeroed: rclpy leaves them as they were in
    memory, so equal messages may differ there. The diagnostics' latencies, measured
    times, are blanked."""
    from rosbags.typesys import Stores, get_typestore

    from lidar_obstacles.ros.offline import OUTPUT_TYPES, _serialize

    store = get_typestore(Stores.ROS2_JAZZY)
    out = []
    for topic, stamp, msg in items:
        kind = OUTPUT_TYPES.get(topic)
        if kind is None:
            continue
        raw = msg if isinstance(msg, bytes) else _serialize(msg)
        decoded = store.deserialize_cdr(raw, kind)
        if topic == "/diagnostics":
            for status in decoded.status:
                for kv in status.values:
                    kv.value = "-" if kv.key.startswith("latency") else kv.value
        out.append((topic, stamp, bytes(store.serialize_cdr(decoded, kind))))
    return out


def _diagnostics(bag: Path) -> dict[str, list[tuple[int, int, dict[str, str]]]]:
    """Per status name, its (stamp ns, level, values) in a bag's /diagnostics."""
    out: dict[str, list] = {}
    with BagReader(bag) as reader:
        for rec in reader.records(["/diagnostics"]):
            msg = reader.deserialize(rec)
            for st in msg.status:
                out.setdefault(st.name, []).append(
                    (offline.messages.stamp_ns_of(msg.header), st.level,
                     {kv.key: kv.value for kv in st.values}))
    return out


def test_diagnostics_warn_on_clouds_dropped_since_the_last_report():
    """The counts cover a node's life; the level only what is new: clouds dropped while a
    node started leave it OK later. A failure (a bug) stays ERROR; no input is WARN."""
    m = offline.messages

    def status(counts, before):
        st = m.diagnostics(m.header(0, ""), "n", "/n", counts, {}, [], 10.0,
                           dropped_before=before).status[0]
        return ord(st.level), st.message  # (a byte in rclpy's message class)

    assert status({"processed": 5, "rejected": 3}, 0) == (1, "3 clouds dropped since the "
                                                          "last report")
    assert status({"processed": 50, "rejected": 3}, 3) == (0, "ok (3 clouds dropped before)")
    assert status({"processed": 50, "rejected": 3, "lost": 1}, 3)[0] == 1
    assert status({"processed": 50}, 0) == (0, "ok")
    # a bug leaves it ERROR for good, and the message says so (it said "ok")
    assert status({"processed": 50, "failed": 1}, 1) == (2, "1 clouds failed on a bug (see "
                                                         "the log)")
    assert status({"processed": 50, "failed": 2}, 1)[1].endswith("; 1 clouds dropped since "
                                                                 "the last report")

    # no cloud since the last report: a dead sensor looked healthy, its latency made up
    def live(received, before):
        st = m.diagnostics(m.header(0, ""), "n", "/n", {"received": received}, {}, [], 0.0,
                           received_before=before).status[0]
        return ord(st.level), st.message, {kv.key: kv.value for kv in st.values}

    assert live(0, 0)[:2] == (1, "no clouds yet")
    assert live(40, 40)[:2] == (1, "no clouds since the last report")
    assert live(50, 40)[:2] == (0, "ok")
    assert live(0, 0)[2]["latency_p50_ms"] == "nan"


def test_replay_writes_each_nodes_diagnostics_on_the_bags_clock(sim_bag, tmp_path):
    """/diagnostics as both nodes would publish it, every second of the bag's time and at
    its end: malformed clouds are counted by the kind of their error (WARN in the report
    after them; two clouds cut short by different lengths are one kind), the points out
    are the clouds' obstacle points and the DEM's ground, the DEM's check points are
    measured."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore

    bad = tmp_path / "two_bad"
    with BagReader(sim_bag) as reader, BagWriter(bad) as out:
        out.add_topic("/points", POINTCLOUD2)
        for i, rec in enumerate(reader.records(["/points"])):
            msg = reader.deserialize(rec)
            if i in (4, 7):
                msg.data = msg.data[: len(msg.data) // (i - 2)]  # a cloud cut short
            out.write("/points", rec.stamp_ns, bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    summary = run_cli("replay", bad, tmp_path / "out", "--skip-malformed")
    assert summary["messages"] == 18 and summary["rejected"] == 2
    assert summary["reject_reasons"] == {"data has N bytes, expected row_step N * height N = N": 2}
    assert summary["last_reject"].startswith("data has ")  # the full one, of cloud 7
    assert summary["last_reject"] != next(iter(summary["reject_reasons"]))
    diag = _diagnostics(tmp_path / "out")
    assert set(diag) == {"obstacle_detector: processing", "dem_builder: processing"}
    obstacle_points = sum(len(c) for c in clouds(tmp_path / "out", "/obstacles"))
    for name, seen in diag.items():
        since = [stamp - offline.SIM_EPOCH_NS for stamp, _, _ in seen]
        assert since == [1_000_000_000, 1_900_000_000]  # 1 s, end
        stamp, level, last = seen[-1]
        # WARN at 1 s, the two clouds dropped since the start; OK at the end, none since
        assert [lvl for _, lvl, _ in seen] == [1, 0]
        assert (last["received"], last["processed"], last["rejected"]) == ("20", "18", "2")
        assert {k: v for k, v in last.items() if k.startswith("dropped: ")} == {
            "dropped: data has N bytes, expected row_step N * height N = N": "2"}
        assert float(last["rate_hz"]) == pytest.approx(10.0, rel=0.15)  # (DEM: the 18 it got)
        assert float(last["latency_p95_ms"]) > 0
    detector = diag["obstacle_detector: processing"][-1][2]
    assert int(detector["points_out"]) == obstacle_points > 0
    dem = diag["dem_builder: processing"][-1][2]
    # in: the clouds' points, as dem_builder counts them (not the detector's ground points
    # that replay hands the DEM)
    assert 0 < int(dem["points_out"]) < int(dem["points_in"]) == summary["points"]
    assert int(dem["check_n"]) > 0 and float(dem["check_rmse_m"]) < 0.2


def test_every_summary_counts_the_finite_points_of_an_organized_cloud(sim_bag, tmp_path):
    """An organized cloud (height > 1) holds NaN points where the scanner had no return:
    no command counts them as points. replay and export-dem counted width x height, where
    evaluate, simplify and features counted the finite points; replay's DEM diagnostics
    counted the ground points the detector handed it, where dem_builder counts the
    cloud's finite points."""
    from lidar_obstacles.config import DemBuilderConfig
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter
    from lidar_obstacles.ros.stages import DemStage

    organized, finite, live = tmp_path / "organized", 0, 0
    with BagReader(sim_bag) as reader, BagWriter(organized) as bag:
        bag.add_topic("/points", POINTCLOUD2)
        for rec in list(reader.records(["/points"]))[:3]:
            msg = reader.deserialize(rec)
            points = np.array(read_points(msg)).reshape(-1)
            width = 1000  # rows of 1000, the last one and one more padded with NaN points
            grid = np.zeros((len(points) // width + 2) * width, points.dtype)
            for axis in "xyz":
                grid[axis] = np.nan
            grid[:len(points)] = points
            cloud = offline.messages.cloud(grid.reshape(-1, width), msg.header)
            assert cloud.height > 1 and cloud.width * cloud.height > len(points) + width
            bag.write("/points", rec.stamp_ns, offline._serialize(cloud))
            finite += len(points)
            live += DemStage(DemBuilderConfig()).process(cloud)["points_in"]  # dem_builder's
    assert live == finite
    replayed = run_cli("replay", organized, tmp_path / "out")
    assert replayed["points"] == finite
    for node in ("obstacle_detector", "dem_builder"):
        diag = _diagnostics(tmp_path / "out")[f"{node}: processing"]
        assert int(diag[-1][2]["points_in"]) == finite, node  # (as the nodes count them)
    assert run_cli("export-dem", organized, tmp_path / "dem.tif")["points"] == finite
    assert run_cli("evaluate", organized, "--no-dem")["n_points"] == finite
    assert run_cli("simplify", organized, tmp_path / "simple")["points_in"] == finite
    assert run_cli("features", organized, tmp_path / "feat")["points_in"] == finite


def _changed_clouds(sim_bag: Path, out: Path, changes: list) -> Path:
    """A bag of the first len(changes) clouds of sim_bag, each points array passed through
    its change (a function that edits it in place)."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore

    with BagReader(sim_bag) as reader, BagWriter(out) as bag:
        bag.add_topic("/points", POINTCLOUD2)
        for change, rec in zip(changes, reader.records(["/points"])):
            msg = reader.deserialize(rec)
            points = np.array(read_points(msg))
            change(points)
            msg.data = np.frombuffer(points.tobytes(), np.uint8)
            bag.write("/points", rec.stamp_ns, bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    return out


def test_replay_makes_stray_points_above_or_below_a_cloud_noise(sim_bag, tmp_path):
    """50 points of a cloud at z = 5 km, -5 km, 1e12, 1e20, 3e38 m: noise (7), never
    ground (5 km up they were wire, 1e20 overflowed the voxel indices: exit 1)."""
    from test_core_inputs import STRAY_Z

    def stray(z):
        def change(points):
            points["z"][:50] = z
        return change

    bag = _changed_clouds(sim_bag, tmp_path / "strays", [stray(z) for z in STRAY_Z])
    summary = offline.replay(bag, tmp_path / "out")
    assert summary["messages"] == len(STRAY_Z) and summary["rejected"] == 0
    ground, obstacles = clouds(tmp_path / "out", "/ground"), clouds(tmp_path / "out", "/obstacles")
    for z, g, o in zip(STRAY_Z, ground, obstacles, strict=True):
        assert not np.isin(g["point_id"], o["point_id"]).any()
        assert (np.abs(g["z"]) < 1000).all()
        stray_points = o[o["z"] == np.float32(z)]
        assert len(stray_points) == 50 and (stray_points["class"] == 7).all(), z
        assert np.isnan(stray_points["height_above_ground"]).all()


def test_a_cloud_record_that_does_not_decode_is_a_malformed_cloud_named_and_skippable(
        sim_bag, tmp_path):
    """A damaged record of the cloud topic (its CDR bytes garbage) stopped replay, evaluate,
    simplify and features with "cannot decode ..." naming no cloud, and --skip-malformed
    could not skip it: one bad message of a long flight cost the whole run. Now it is a
    malformed cloud: named by its number and the record's time, and skipped on request."""
    from lidar_obstacles.evaluate import evaluate
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter
    from lidar_obstacles.ros.cloud_tools import simplify

    bad = tmp_path / "garbled"
    with BagReader(sim_bag) as reader, BagWriter(bad) as out:
        out.add_topic("/points", POINTCLOUD2)
        for i, rec in enumerate(reader.records(["/points"])):
            raw = b"\x00\x01\x00\x00" + b"\xff" * 12 if i == 2 else rec.raw
            out.write("/points", rec.stamp_ns, raw)
    named = (r"^cloud 3 on /points \(stamp 1767225600\.200000000 s\): cannot decode a "
             r"sensor_msgs/msg/PointCloud2 message on /points: .*--skip-malformed")
    with pytest.raises(CloudFormatError, match=named):
        offline.replay(bad, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    summary = offline.replay(bad, tmp_path / "out", skip_malformed=True)
    assert summary["messages"] == 19 and summary["rejected"] == 1
    assert summary["last_reject"].startswith("cannot decode a sensor_msgs/msg/PointCloud2")
    with pytest.raises(CloudFormatError, match=named):
        evaluate(bad, with_dem=False)
    result = evaluate(bad, with_dem=False, skip_malformed=True)
    assert result["clouds"] == 19 and result["rejected"] == 1
    with pytest.raises(CloudFormatError, match=named):
        simplify(bad, tmp_path / "simple")
    assert not (tmp_path / "simple").exists()
    assert simplify(bad, tmp_path / "simple", skip_malformed=True)["messages"] == 19


def test_replay_refuses_a_cloud_too_big_for_its_grids_with_the_reason(sim_bag, tmp_path):
    """Half a cloud 1e15 m above the other half (not a few strays: half of it) overflowed
    its int64 voxel indices (exit 1); now it is rejected and counted, the others replayed."""
    def keep(points):
        pass

    def apart(points):
        points["z"][::2] += np.float32(1e15)

    bag = _changed_clouds(sim_bag, tmp_path / "apart", [keep, apart, keep])
    with pytest.raises(CloudFormatError, match=r"^cloud 2 on /points \(stamp 1767225600\.1"
                       r"00000000 s\): the cloud spans 1e\+15 m in z"):
        offline.replay(bag, tmp_path / "out")  # (by default: stop, as on any bad input)
    assert not (tmp_path / "out").exists()
    summary = offline.replay(bag, tmp_path / "out", skip_malformed=True)
    assert summary["messages"] == 2 and summary["rejected"] == 1
    assert summary["reject_reasons"] == {"the cloud spans N m in z, more than N m": 1}
    assert summary["last_reject"].startswith("the cloud spans 1e+15 m in z")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_replay_in_three_processes_writes_exactly_what_a_sequential_run_makes(
        sim_bag, tmp_path, storage):
    """The detector's second half and the DEM run in processes of their own, the writing
    on a thread, and change nothing: same messages, same order, as doing everything one
    cloud after the other in one process. In either storage: sqlite3 lets only the thread
    that opened the bag write it."""
    from lidar_obstacles.config import DemBuilderConfig, ObstacleDetectorConfig
    from lidar_obstacles.ros.offline import DemSchedule, ReplayStats, drain, replay, run_stages
    from lidar_obstacles.ros.stages import DemStage, DetectorStage

    replay(sim_bag, tmp_path / "parallel", storage=storage)
    suffix = {"mcap": ".mcap", "sqlite3": ".db3"}[storage]
    assert [p.suffix for p in (tmp_path / "parallel").iterdir() if p.suffix != ".yaml"] == [suffix]
    with BagReader(tmp_path / "parallel") as reader:
        written = [(r.topic, r.stamp_ns, r.raw) for r in reader.records()]
    with BagReader(sim_bag) as reader:
        detector, dem = DetectorStage(ObstacleDetectorConfig()), DemStage(DemBuilderConfig())
        schedule, stats = DemSchedule(dem), ReplayStats()
        sequential = [done for item in run_stages(
            reader, topic=None, detector=detector, dem=dem, stats=stats)
            for done in drain(item, detector=detector, schedule=schedule, stats=stats)]
    assert any(t == "/dem" for t, _, _ in sequential)
    assert _contents(written) == _contents(sequential)


def test_a_worker_process_hands_its_errors_back():
    """An exception in a worker process is raised where its result is awaited (the
    writer thread, which hands it to replay: see the failing-write test)."""
    from lidar_obstacles.config import DemBuilderConfig, ObstacleDetectorConfig
    from lidar_obstacles.ros.offline import DemWork, _WorkerProcesses

    workers = _WorkerProcesses(ObstacleDetectorConfig(), DemBuilderConfig())
    try:
        ok = workers.submit(DemWork(0, 0, "map", None, np.zeros((3, 3)), np.zeros(3)))
        assert ok.result(timeout=120).items == []  # the first cloud: no DEM due yet
        bad = workers.submit(DemWork(1, 1, "map", None, np.zeros((5, 2)), np.zeros(5)))
        with pytest.raises(ValueError, match="reshape"):
            bad.result(timeout=120)
    finally:
        workers.close()


def test_a_failing_write_stops_replay_with_its_error(sim_bag, tmp_path, monkeypatch):
    from multiprocessing.shared_memory import SharedMemory

    from lidar_obstacles.io.bags import BagWriter
    from lidar_obstacles.io.shared_pickle import NAME_PREFIX
    from lidar_obstacles.ros.offline import replay

    others: list[SharedMemory] = []

    def broken(self, topic, stamp_ns, raw):
        # another program's block, made while the replay runs (all of /dev/shm was
        # compared: another process's replay or test failed this one)
        others.append(SharedMemory(create=True, size=1))
        raise OSError("disk full")

    def ours() -> set[Path]:  # (its workers' too: forked, they name blocks the same)
        return set(Path("/dev/shm").glob(NAME_PREFIX + "*"))

    monkeypatch.setattr(BagWriter, "write", broken)
    assert NAME_PREFIX.startswith("lidar_obstacles_") and NAME_PREFIX.endswith(f"_{os.getpid()}_")
    shared_before = ours()
    try:
        with pytest.raises(OSError, match="disk full"):
            replay(sim_bag, tmp_path / "out")
        assert list(tmp_path.iterdir()) == []  # nothing half-written left behind
        # nor any cloud or result left in shared memory by the work cut short
        assert ours() <= shared_before
        assert Path("/dev/shm", others[0].name.lstrip("/")).exists()  # (but not counted)
    finally:
        for block in others:
            block.close()
            block.unlink()


@pytest.mark.slow
@pytest.mark.parametrize("name", SHARED_FILES)
def test_las2bag_and_replay_every_shared_file(name, tmp_path):
    src = data_file(name)
    bag = tmp_path / "bag"
    summary = run_cli("las2bag", src, bag)
    from lidar_obstacles.io.las import read_las

    las = read_las(src)
    got = clouds(bag, "/points")
    assert summary["points"] == len(las.points) == sum(len(c) for c in got)
    ids = np.sort(np.concatenate([c["point_id"] for c in got]))
    assert (ids == np.arange(len(las.points))).all()
    first = got[0]
    assert first.dtype["x"] == np.float64
    # each field at a multiple of its size, the point a multiple of 8 bytes (C++ readers)
    assert first.dtype.itemsize % 8 == 0
    assert all(offset % first.dtype[name].itemsize == 0
               for name, (_, offset) in first.dtype.fields.items())
    np.testing.assert_array_equal(first["x"], las.points["x"][first["point_id"]])
    np.testing.assert_array_equal(first["classification"],
                                  las.points["classification"][first["point_id"]])
    if las.has_gps_time and np.ptp(las.points["gps_time"]) > 0:
        assert summary["sliced_by"] == "gps_time"
        for c in got[:20]:
            assert np.ptp(c["gps_time"]) < 0.1 + 1e-9
    out = tmp_path / "out"
    replayed = run_cli("replay", bag, out, "--no-dem")
    assert replayed["messages"] == summary["messages"] and replayed["rejected"] == 0


def test_las2bag_slices_by_flight_line_without_gps_time():
    from lidar_obstacles.ros.offline import _las_slices

    # two overlapping lines, flown east-west then north-south, the second first in the file
    rng = np.random.default_rng(0)
    n = 4000
    pts = np.zeros(2 * n, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                 ("point_source_id", "<u2")])
    pts["x"][:n], pts["y"][:n] = rng.uniform(0, 30, n), rng.uniform(0, 300, n)
    pts["point_source_id"][:n] = 9
    pts["x"][n:], pts["y"][n:] = rng.uniform(0, 300, n), rng.uniform(0, 30, n)
    pts["point_source_id"][n:] = 4
    groups, stamps, how = _las_slices(pts, has_gps=False, slice_seconds=0.1, tile_size=None,
                                      strip_width=10.0)
    assert how == "flight_lines" and (np.diff(stamps) > 0).all()
    lines = [np.unique(pts["point_source_id"][g]) for g in groups]
    assert all(len(u) == 1 for u in lines)  # never two lines in one message
    order = [int(u[0]) for u in lines]
    assert order == sorted(order, key=[9, 4].index)  # line 9 (first in the file) first
    for g in groups:  # strips across each line's own length
        line = pts[g]
        along = line["y"] if line["point_source_id"][0] == 9 else line["x"]
        assert np.ptp(along) <= 10.0
    assert sum(len(g) for g in groups) == 2 * n


@pytest.mark.parametrize("outlier", [5e9, 1e12, np.nan, np.inf])
def test_las2bag_refuses_gps_times_past_what_a_stamp_holds(tmp_path, outlier):
    """One corrupt GPS time: at 5e9 s its cloud's header stamp wrapped round to a negative
    one; at 1e12 s the bag's clock overflowed (OverflowError, a traceback); NaN made the
    survey go to strips without a word."""
    import laspy

    las = laspy.read(str(data_file("isprs/samp11-utm.laz")))
    survey = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
    survey.header.offsets, survey.header.scales = las.header.offsets, las.header.scales
    survey.x, survey.y, survey.z = las.x, las.y, las.z
    gps = np.linspace(0.0, 60.0, len(las.points))
    gps[3] = outlier
    survey.gps_time = gps
    survey.write(str(tmp_path / "survey.las"))
    res = cli_subprocess("las2bag", tmp_path / "survey.las", tmp_path / "bag")
    assert res.returncode == 2, res.stderr
    assert res.stderr.splitlines()[-1].startswith(
        f"lidar-obstacles las2bag: error: GPS time {outlier:.10g} s gives a stamp past 2038"
        if np.isfinite(outlier) else
        "lidar-obstacles las2bag: error: GPS time not finite at 1 of ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["survey.las"]
    tiled = run_cli("las2bag", tmp_path / "survey.las", tmp_path / "bag", "--tile-size", "50")
    assert tiled["sliced_by"] == "tiles"


@pytest.mark.parametrize("outlier", [-5e9, -1e300, 1e300])
def test_las2bag_refuses_gps_times_before_what_a_stamp_holds(tmp_path, outlier):
    """A GPS time before the GPS epoch (adjusted time below -1e9 s) gave a stamp before
    1970, written as 0, which ROS reads as unset: every cloud of the bag stamped 0, without
    a word. One of -1e300 s or 1e300 s also printed numpy's RuntimeWarning of the
    overflowing slice numbers before the error's line."""
    import laspy

    survey = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
    survey.x, survey.y, survey.z = (np.linspace(0.0, 100.0, 1000),) * 3
    gps = np.linspace(0.0, 60.0, 1000)
    gps[3] = outlier
    survey.gps_time = gps
    survey.write(str(tmp_path / "survey.las"))
    res = cli_subprocess("las2bag", tmp_path / "survey.las", tmp_path / "bag")
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.splitlines()) == 1, res.stderr
    assert res.stderr.startswith(
        f"lidar-obstacles las2bag: error: GPS time {outlier:.10g} s gives a stamp "
        + ("before 1970" if outlier < 0 else "past 2038"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["survey.las"]


def _stamps(bag: Path) -> list[int]:
    with BagReader(bag) as reader:
        return [reader.deserialize(r).header.stamp.sec * 10**9
                + reader.deserialize(r).header.stamp.nanosec
                for r in reader.records(["/points"])]


@pytest.mark.parametrize("adjusted, gps_start, first_utc", [
    # adjusted standard GPS time, as the header's global encoding says: 86 400 s is 1e9 +
    # 86 400 GPS seconds, 2011-09-15, when GPS ran 15 s ahead of UTC; it was taken for
    # seconds of a week, and stamped 1970-01-02
    (True, 86400.0, "2011-09-15T01:46:25"),
    # 2019 (18 leap seconds): as before
    (True, 2.6e8, "2019-12-10T07:59:42"),
    # seconds of a GPS week the file does not name: from the day the file was made
    (False, 3600.0, "2024-03-05T00:00:00"),
    # no time at all: slices from that day too; the first was stamped 0, "unset" in ROS
    (False, None, "2024-03-05T00:00:00"),
])
def test_las2bag_stamps_are_utc_or_start_on_the_files_day(tmp_path, adjusted, gps_start,
                                                          first_utc):
    import datetime

    import laspy

    header = laspy.LasHeader(point_format=1 if gps_start is not None else 0, version="1.2")
    header.global_encoding.gps_time_type = (laspy.header.GpsTimeType.STANDARD if adjusted
                                            else laspy.header.GpsTimeType.WEEK_TIME)
    header.creation_date = datetime.date(2024, 3, 5)
    survey = laspy.LasData(header)
    rng = np.random.default_rng(0)
    survey.x, survey.y = rng.uniform(0, 40, 3000), rng.uniform(0, 40, 3000)
    survey.z = np.zeros(3000)
    if gps_start is not None:
        survey.gps_time = gps_start + np.linspace(0, 0.5, 3000)
    survey.write(str(tmp_path / "survey.las"))
    run_cli("las2bag", tmp_path / "survey.las", tmp_path / "bag")
    stamps = _stamps(tmp_path / "bag")
    first = datetime.datetime.fromtimestamp(stamps[0] // 10**9, datetime.timezone.utc)
    assert first.strftime("%Y-%m-%dT%H:%M:%S") == first_utc
    assert (np.diff(stamps) > 0).all()


def test_las2bag_tiles(tmp_path):
    src = data_file("isprs/samp11-utm.laz")
    summary = run_cli("las2bag", src, tmp_path / "bag", "--tile-size", "50")
    assert summary["sliced_by"] == "tiles"
    tiles = clouds(tmp_path / "bag", "/points")
    assert len(tiles) >= 12 and sum(len(c) for c in tiles) == 38010  # every point, once
    for c in tiles:
        assert np.ptp(c["x"]) <= 50 and np.ptp(c["y"]) <= 50


def test_export_dem_says_why_no_cloud_could_be_used(sim_bag, tmp_path):
    """Every cloud over `input.max_points`: the reason, not "no ground found"."""
    params = tmp_path / "small.yaml"
    params.write_text("/**:\n  ros__parameters:\n    input.max_points: 100\n")
    res = cli_subprocess("export-dem", sim_bag, tmp_path / "dem.tif", "--params-file", params)
    assert res.returncode == 2 and res.stderr.startswith(
        "lidar-obstacles export-dem: error: cloud 1 on /points (stamp 1767225600.000000000 s): "
        "cloud has ")
    assert "points, more than input.max_points=100 (--skip-malformed" in res.stderr
    res = cli_subprocess("export-dem", sim_bag, tmp_path / "dem.tif", "--params-file", params,
                         "--skip-malformed")
    assert res.returncode == 2 and "20 rejected" in res.stderr
    assert "more than input.max_points" in res.stderr and "no ground" not in res.stderr
    assert not (tmp_path / "dem.tif").exists()


def test_export_dem_of_more_than_max_cells_is_an_error_not_a_window(sim_bag, tmp_path):
    # over dem.max_cells the rolling grid became a window round the last cloud, and the
    # survey's first part was left out of the GeoTIFF without a word
    params = tmp_path / "few.yaml"
    params.write_text("/**:\n  ros__parameters:\n    dem.max_cells: 2000\n")
    res = cli_subprocess("export-dem", sim_bag, tmp_path / "dem.tif", "--params-file", params)
    # the span of the whole survey, not of the ground seen when the grid grew too large
    # (it named the first clouds' ground, rounded up to blocks of 64 cells)
    with BagReader(sim_bag) as reader:
        xy = np.concatenate([np.column_stack([p["x"], p["y"]]) for p in (
            read_points(reader.deserialize(r)) for r in reader.records(["/points"]))])
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    cells = int(np.prod(np.floor(hi) - np.floor(lo) + 1))
    said = re.fullmatch(
        r"lidar-obstacles export-dem: error: the survey spans (\d+) x (\d+) m: (\d+) cells of "
        r"dem.resolution 1 m, over dem.max_cells = 2000; raise it to (\d+) \(~32 bytes a "
        r"cell: \S+ GB\) or coarsen dem.resolution to ([\d.]+) m\n", res.stderr)
    assert res.returncode == 2 and said, res.stderr
    assert [int(v) for v in said.groups()[:4]] == [*np.round(hi - lo).astype(int), cells, cells]
    assert list(tmp_path.iterdir()) == [params]
    # and what it says works: at the resolution it names, the DEM fits
    params.write_text("/**:\n  ros__parameters:\n    dem.max_cells: 2000\n"
                      f"    dem.resolution: {said.group(5)}\n")
    res = cli_subprocess("export-dem", sim_bag, tmp_path / "dem.tif", "--params-file", params)
    assert res.returncode == 0, res.stderr
    # the live node's DEM still rolls on as a window (a flight has no end)
    from lidar_obstacles.config import DemBuilderConfig, replace
    from lidar_obstacles.core.dem import RollingDem

    dem = RollingDem(replace(DemBuilderConfig(), {"dem.extent": 0.0, "dem.max_cells": 2000}))
    for x0 in (0.0, 500.0):
        dem.update(np.column_stack([np.random.default_rng(1).uniform(x0, x0 + 20, (500, 2)),
                                    np.zeros(500)]))
    assert dem.snapshot().elevation.size <= 2000


def _with_crs(src: Path, out: Path, crs: str) -> Path:
    """A copy of bag `src` with `crs` on /survey_crs, as las2bag records a survey's."""
    from std_msgs.msg import String

    from lidar_obstacles.io.bags import CRS_TOPIC, BagWriter

    with BagReader(src) as reader, BagWriter(out) as bag:
        bag.add_topic(CRS_TOPIC, offline.STRING, transient_local=True)
        bag.write(CRS_TOPIC, 1, offline._serialize(String(data=crs)))
        for t in reader.topics():
            bag.add_topic(t.topic, t.msgtype)
        for record in reader.records([t.topic for t in reader.topics()]):
            bag.write(record.topic, record.stamp_ns, record.raw)
    return out


def test_export_dem_writes_no_crs_the_dem_cannot_be_in_and_says_so(sim_bag, tmp_path):
    from lidar_obstacles.io.geotiff import read_geotiff

    bag = _with_crs(sim_bag, tmp_path / "lonlat", "EPSG:4326")
    res = cli_subprocess("export-dem", bag, tmp_path / "dem.tif")
    assert res.returncode == 0, res.stderr
    assert ("export-dem: warning: the survey's CRS (/survey_crs in the bag) is not written: "
            "EPSG:4326 is geographic (WGS 84): its x and y are degrees") in res.stderr
    assert json.loads(res.stdout)["crs"] == ""
    assert read_geotiff(tmp_path / "dem.tif").epsg is None
    # given on the command line, it is refused before the work
    res = cli_subprocess("export-dem", bag, tmp_path / "b.tif", "--crs", "EPSG:4326")
    assert res.returncode == 2 and res.stderr == (
        "lidar-obstacles export-dem: error: --crs: EPSG:4326 is geographic (WGS 84): its x "
        "and y are degrees, the DEM's cells metres; give the projected CRS of the points\n")


def test_a_survey_crs_topic_of_another_type_is_no_crs_and_said(sim_bag, tmp_path, caplog):
    """/survey_crs recorded as a PointCloud2 (not las2bag's String): its uint8 data was
    read as the CRS and printed, an array of numbers, in export-dem's warning."""
    from lidar_obstacles.io.bags import CRS_TOPIC, POINTCLOUD2, BagWriter, read_crs

    bag = tmp_path / "crs_cloud"
    with BagReader(sim_bag) as reader, BagWriter(bag) as out:
        out.add_topic(CRS_TOPIC, POINTCLOUD2)
        out.add_topic("/points", POINTCLOUD2)
        for record in reader.records(["/points"]):
            out.write("/points", record.stamp_ns, record.raw)
            out.write(CRS_TOPIC, record.stamp_ns, record.raw)
    with BagReader(bag) as reader:
        assert read_crs(reader) == ""
    assert (f"/survey_crs of {bag} is a sensor_msgs/msg/PointCloud2, not the "
            "std_msgs/msg/String that las2bag writes: no survey CRS taken from it"
            in caplog.text)
    summary = run_cli("export-dem", bag, tmp_path / "dem.tif")
    assert summary["crs"] == ""


def test_export_dem_lands_on_survey_coordinates(tmp_path):
    src = data_file("isprs/samp51-utm.laz")
    run_cli("las2bag", src, tmp_path / "bag")
    summary = run_cli("export-dem", tmp_path / "bag", tmp_path / "dem.tif")
    assert summary["crs"] == "EPSG:32632"
    from lidar_obstacles.io.geotiff import read_geotiff
    from lidar_obstacles.io.las import read_las

    dem = read_geotiff(tmp_path / "dem.tif")
    las = read_las(src).points
    x0, y_top = dem.origin[0], dem.origin[1] + dem.elevation.shape[0] * dem.resolution
    # the grid is aligned to whole cells and cut to where there is elevation
    assert -1.0 < las["x"].min() - x0 < 1.0 and -1.0 < y_top - las["y"].max() < 1.0
    assert (tmp_path / "dem_hillshade.png").stat().st_size > 1000
    # a params file that does not set dem.extent still gives the whole survey (it gave the
    # rolling window of the last 200 m)
    params = tmp_path / "tin.yaml"
    params.write_text("/**:\n  ros__parameters:\n    dem.interpolation: tin\n")
    again = run_cli("export-dem", tmp_path / "bag", tmp_path / "tin.tif", "--params-file", params)
    assert (again["rows"], again["cols"]) == (summary["rows"], summary["cols"])
    assert summary["rows"] * summary["resolution"] > 250  # more than one window
    # the shipped config sets the live node's window: kept, and said
    shipped = cli_subprocess("export-dem", tmp_path / "bag", tmp_path / "win.tif",
                             "--params-file", REPO / "config" / "dem_builder.yaml")
    assert shipped.returncode == 0 and "dem.extent is 200 m" in shipped.stderr
    assert json.loads(shipped.stdout)["rows"] < summary["rows"]


def test_export_dem_replaces_its_own_outputs_and_nothing_else(sim_bag, tmp_path, capsys):
    tif, png = tmp_path / "dem.tif", tmp_path / "dem_hillshade.png"
    run_cli("export-dem", sim_bag, tif)
    written = tif.read_bytes(), png.read_bytes()
    run_cli("export-dem", sim_bag, tif)  # a TIFF and a PNG are replaced
    assert tif.read_bytes()[:4] == b"II*\0" and png.read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()
    notes = tmp_path / "afile.txt"
    for target, victim in ((notes, notes), (tif, tif), (tif, png)):
        victim.write_text("precious\n")
        assert main(["export-dem", str(sim_bag), str(target)]) == 2
        kind = "a PNG" if victim == png else "a TIFF"
        assert capsys.readouterr().err == (f"lidar-obstacles export-dem: error: {victim} exists "
                                           f"and is not {kind}: not overwriting it\n")
        assert victim.read_text() == "precious\n"
        victim.write_bytes(written[victim == png])
    assert tif.read_bytes() == written[0]  # the TIFF left alone when its hillshade is refused
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile.txt", tif.name, png.name]


@pytest.mark.parametrize("args, expected", [
    (["replay", "/nonexistent/bag", "OUT"], "bag not found"),
    (["las2bag", "/nonexistent.laz", "OUT"], "LAS file not found"),
    (["export-dem", "/nonexistent/bag", "OUT.tif"], "bag not found"),
    (["simulate", "OUT", "--scene", "moon"], "invalid choice: 'moon'"),  # a usage mistake
    (["demo", "--duration", "-1"], "must lie in [0.001, 1e+06]"),
    (["las2bag", "/nonexistent.laz", "OUT", "--frame-id", ""], "not a valid frame id"),
    (["replay", "/nonexistent/bag", "OUT", "--bogus"],
     "unrecognized arguments: --bogus (see lidar-obstacles replay --help)"),
    (["simulate", "OUT", "--points", "0"], "argument --points: must lie in [100, 1e+06]"),
    (["las2bag", "/nonexistent.laz", "OUT", "--frame-id", "/map"], "not a valid frame id"),
    # (the search ran, tried nothing and blamed the budget)
    (["tune", "/nonexistent/bag", "--trials", "0"], "argument --trials: must lie in [1, "),
])
def test_bad_input_is_one_line_and_exit_2(args, expected, tmp_path):
    res = cli_subprocess(*[a.replace("OUT", str(tmp_path / "o")) for a in args])
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], res.stderr
    assert not list(tmp_path.iterdir())


def test_demo_never_makes_its_folder_over_a_file(tmp_path):
    notes = tmp_path / "afile.txt"
    notes.write_text("precious\n")
    for out, expected in ((notes, f"{notes} exists and is not a folder: not overwriting it"),
                          (notes / "demo", f"cannot make the output folder {notes / 'demo'}: "
                                           "Not a directory")):
        res = cli_subprocess("demo", "--out", out, "--duration", "0.3")
        assert res.returncode == 2
        assert res.stderr == f"lidar-obstacles demo: error: {expected}\n"
    assert notes.read_text() == "precious\n"


def test_corrupt_bag_and_bad_params_exit_2(sim_bag, tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 100)
    res = cli_subprocess("replay", junk, tmp_path / "o")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1
    # a record's length field overwritten: Python's own "int too large to convert to C
    # ssize_t" came through
    import shutil

    shutil.copytree(sim_bag, tmp_path / "garbled")
    (mcap,) = (tmp_path / "garbled").glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    data[100:116] = b"\xff" * 16
    mcap.write_bytes(bytes(data))
    res = cli_subprocess("replay", tmp_path / "garbled", tmp_path / "o")
    assert res.returncode == 2 and res.stderr == (
        f"lidar-obstacles replay: error: bag {tmp_path / 'garbled'} is truncated or corrupt: "
        "a record's length is out of range\n")
    params = tmp_path / "bad.yaml"
    params.write_text("/**:\n  ros__parameters:\n    ransac:\n      distance_threshold: -3.0\n")
    res = cli_subprocess("replay", sim_bag, tmp_path / "o", "--params-file", params)
    assert res.returncode == 2
    assert "ransac.distance_threshold" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


class _Graph:
    """Stands in for a node's graph queries: the subscriptions change at given times."""

    def __init__(self, script: list[tuple[float, list]]) -> None:
        self.t0 = time.monotonic()
        self.script = script

    def get_subscriptions_info_by_topic(self, topic: str) -> list:
        now = time.monotonic() - self.t0
        return [s for t, subs in self.script if t <= now for s in subs][-1:]


def _sub(name: str, reliability: int) -> SimpleNamespace:
    return SimpleNamespace(node_namespace="/uav1", node_name=name,
                           qos_profile=SimpleNamespace(reliability=reliability))


def test_play_waits_for_subscriptions_to_settle():
    # A subscriber appears best effort at 0.1 s and turns reliable at 0.5 s (a node on
    # `input.reliability: auto`): play starts only after a quiet period past the switch.
    graph = _Graph([(0.1, [_sub("det", 2)]), (0.5, [_sub("det", 1)])])
    t0 = time.monotonic()
    assert offline._subscriptions_settled(graph, ["/uav1/points"], quiet_s=0.6, timeout_s=5)
    assert time.monotonic() - t0 >= 1.1
    # Nobody subscribes: give up after the timeout.
    t0 = time.monotonic()
    assert not offline._subscriptions_settled(_Graph([]), ["/uav1/points"], quiet_s=0.2,
                                              timeout_s=0.5)
    assert time.monotonic() - t0 >= 0.5


class _Topics:
    """Stands in for a node's graph queries: topic -> number of subscribers."""

    def __init__(self, subscribers: dict[str, int]) -> None:
        self.subscribers = subscribers

    def get_topic_names_and_types(self) -> list:
        return [(t, ["sensor_msgs/msg/PointCloud2"]) for t in self.subscribers]

    def count_subscribers(self, topic: str) -> int:
        return self.subscribers[topic]


def test_play_without_subscribers_names_the_namespaces_that_have_them():
    # play published /points while the nodes ran under /uav1 and /uav2: it said only
    # "no steady subscriber", 15 s later, with nothing to tell why
    graph = _Topics({"/uav1/points": 1, "/uav2/points": 2, "/points": 0, "/uav3/points": 0,
                     "/uav1/odom": 1, "/lidar/front/points": 1})
    assert offline._elsewhere_hint(graph, {"/points": "/points"}) == (
        "; subscribed elsewhere: /lidar/front/points, /uav1/points, /uav2/points "
        "(--namespace /lidar/front or --namespace /uav1 or --namespace /uav2?)")
    # into the wrong namespace; and a bag topic one level deeper, reached only by a remap
    assert offline._elsewhere_hint(_Topics({"/points": 1, "/uav2/points": 0}),
                                   {"/points": "/uav2/points"}) == (
        "; subscribed elsewhere: /points (no --namespace?)")
    assert offline._elsewhere_hint(_Topics({"/uav1/points": 1}),
                                   {"/ouster/points": "/ouster/points"}) == (
        "; subscribed elsewhere: /uav1/points")
    # nobody anywhere: nothing to add
    assert offline._elsewhere_hint(_Topics({"/uav1/points": 0}), {"/points": "/points"}) == ""


def _children(pid: int) -> list[int]:
    """The child processes of `pid` (Linux /proc)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass  # (a thread gone meanwhile)
    return out


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux /proc")
def test_replay_killed_outright_takes_its_workers_with_it(tmp_path):
    # kill -9 (or the OOM killer) gives the parent no chance to stop its workers: they
    # waited for work for good, holding their memory
    run_cli("simulate", tmp_path / "f", "--duration", "10", "--seed", "4")
    proc = subprocess.Popen([sys.executable, "-m", "lidar_obstacles.cli", "replay",
                             str(tmp_path / "f"), str(tmp_path / "out")], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60  # until it writes (its workers are forked by then)
    while not list(tmp_path.glob(".out.partial-*")) and time.monotonic() < deadline:
        time.sleep(0.05)
    workers = [c for c in _children(proc.pid)
               if "resource_tracker" not in Path(f"/proc/{c}/cmdline").read_text()]
    assert proc.poll() is None and len(workers) == 2, "replay finished before it was killed"
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [w for w in workers if Path(f"/proc/{w}").exists()
            and Path(f"/proc/{w}/stat").read_text().split(") ")[1][0] != "Z"]
    for w in left:
        os.kill(w, signal.SIGKILL)
    assert not left, "worker processes left running"


def test_sigterm_during_replay_leaves_nothing_behind(tmp_path):
    # as on Ctrl-C: the worker processes stop and the partial bag goes (exit 128 + 15)
    run_cli("simulate", tmp_path / "f", "--duration", "10", "--seed", "4")
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "lidar_obstacles.cli", "replay",
                             str(tmp_path / "f"), str(out)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60  # until it writes (its workers are forked by then)
    while not list(tmp_path.glob(".out.partial-*")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)  # a few clouds in, most of the 100 to go
    assert proc.poll() is None, "replay finished before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    # (a shared-memory block in flight at that moment is freed by multiprocessing's
    # resource tracker, which says so on stderr)
    assert "lidar-obstacles replay: terminated" in err.strip().splitlines()
    time.sleep(0.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # no bag, no partial one
    left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True)
    assert left.stdout.strip() == "", "worker processes left running"


def test_a_cloud_with_an_unset_stamp_leaves_the_bags_span_as_recorded(sim_bag, tmp_path):
    """One cloud of a bag stamped 0 (unset) in its header made its span 70 years: the
    summary said bag_seconds 2.2e9 and 2e9 x real time. The span is the bag's own times."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore

    bag = tmp_path / "unset"
    with BagReader(sim_bag) as reader, BagWriter(bag) as out:
        out.add_topic("/points", POINTCLOUD2)
        for i, rec in enumerate(reader.records(["/points"])):
            msg = reader.deserialize(rec)
            if i == 3:
                msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
            out.write("/points", rec.stamp_ns, bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    summary = offline.replay(bag, tmp_path / "out", with_dem=False)
    assert summary["messages"] == 20
    assert summary["bag_seconds"] == pytest.approx(2.0)  # 20 clouds at 10 Hz
    assert summary["real_time_factor"] < 1000


def test_clouds_without_a_frame_id_are_said_once(sim_bag, tmp_path):
    """Clouds with frame_id '' were processed and their outputs went out with no frame,
    which RViz and tf cannot place, without a word."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore
    from lidar_obstacles.ros.stages import missing_frame_warning

    bag = tmp_path / "frameless"
    with BagReader(sim_bag) as reader, BagWriter(bag) as out:
        out.add_topic("/points", POINTCLOUD2)
        for rec in list(reader.records(["/points"]))[:5]:
            msg = reader.deserialize(rec)
            msg.header.frame_id = ""
            out.write("/points", rec.stamp_ns, bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    res = cli_subprocess("replay", bag, tmp_path / "out", "--no-dem")
    assert res.returncode == 0, res.stderr
    said = [line for line in res.stderr.splitlines() if "no frame_id" in line]
    assert said == [f"replay: warning: {missing_frame_warning('')}"]
    assert missing_frame_warning("map") is None and missing_frame_warning("/") is not None
