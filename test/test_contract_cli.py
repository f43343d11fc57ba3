"""The contract's `lidar-obstacles` subcommands run as a user runs them: `demo` writes what
it says and says where, `play --loop` plays a bag again and again until Ctrl-C."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, signal_when


def _cli(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lidar_obstacles.cli", *map(str, args)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_demo_writes_the_bags_dem_and_report_and_says_where(tmp_path):
    out = tmp_path / "demo"
    proc = _cli("demo", "--duration", "2", "--out", out)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout)
    named = {key: Path(summary[key]) for key in
             ("flight_bag", "output_bag", "dem_geotiff", "dem_hillshade", "report")}
    assert named == {"flight_bag": out / "flight", "output_bag": out / "replayed",
                     "dem_geotiff": out / "dem.tif", "dem_hillshade": out / "dem_hillshade.png",
                     "report": out / "report" / "report.html"}
    assert stderr.rstrip().endswith(
        f"Demo done. Open {named['report']} for the pictures; outputs in {out}/")
    # the bags: rosbag2 folders with their metadata and a non-empty mcap each
    for bag in (named["flight_bag"], named["output_bag"]):
        assert (bag / "metadata.yaml").stat().st_size > 0, bag
        assert [p.stat().st_size > 1000 for p in bag.glob("*.mcap")] == [True], bag
    assert summary["messages"] == 20 and summary["points"] > 100000
    with open(named["dem_geotiff"], "rb") as f:
        assert f.read(4) in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+")  # a TIFF
    png = b"\x89PNG\r\n\x1a\n"
    assert named["dem_hillshade"].read_bytes()[:8] == png
    # the report: its pictures beside it and in it, and its metrics
    report = named["report"].parent
    pictures = sorted(report.glob("*.png"))
    assert len(pictures) >= 5, pictures
    assert all(p.read_bytes()[:8] == png for p in pictures)
    html = named["report"].read_text()
    assert html.count("data:image/png;base64,") == len(pictures)
    metrics = json.loads((report / "metrics.json").read_text())
    assert 0.9 < metrics["ground_object"]["kappa"] <= 1.0
    assert metrics["ground_object"]["kappa"] == summary["ground_kappa"]


rclpy = pytest.importorskip("rclpy")

from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402


def test_play_loop_plays_the_bag_again_until_ctrl_c(ros_node, tmp_path):
    from lidar_obstacles.ros import offline

    bag, ns = tmp_path / "bag", "/contract_play_loop"
    made = offline.simulate(bag, scene="mixed", seed=1, duration=0.3, frame="map",
                            points_per_frame=1000)
    held = made["messages"]
    assert held == 3
    got: list = []
    sub = ros_node.create_subscription(PointCloud2, f"{ns}/points", got.append,
                                       QoSProfile(depth=50,
                                                  reliability=ReliabilityPolicy.RELIABLE))
    proc = _cli("play", bag, "--loop", "--topics", "/points", "--namespace", ns)

    def looped() -> None:
        # three times what the bag holds: it started again, twice
        deadline = time.monotonic() + 60
        while len(got) <= 3 * held:
            assert time.monotonic() < deadline and proc.poll() is None, (len(got), proc.poll())
            rclpy.spin_once(ros_node, timeout_sec=0.1)

    try:
        out, err = signal_when(proc, looped, signal.SIGINT, timeout=30)
    finally:
        ros_node.destroy_subscription(sub)
    assert proc.returncode == 130 and out == "", err
    said = re.fullmatch(r"lidar-obstacles play: interrupted \(published: (\d+)\)\n", err)
    assert said, err
    assert int(said[1]) >= len(got) > 3 * held
    # the same clouds again, in the bag's order
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got]
    assert len(set(stamps)) == held
    assert stamps[:2 * held] == stamps[:held] * 2


def _play_to_the_end(node, proc: subprocess.Popen, timeout: float = 120) -> tuple[str, str]:
    """Spin `node` (its subscribers acknowledge what `play` sends) until `play` exits; its
    (stdout, stderr). Killed if it has not ended within `timeout`."""
    try:
        deadline = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.communicate(timeout=30)


@pytest.mark.slow
def test_play_clock_publishes_the_bags_time_on_clock(ros_node, tmp_path):
    # Nothing published /clock: a node with use_sim_time never saw its time advance. It is
    # /clock whatever the namespace (as ros2 bag play's), best effort as rclpy's
    # TimeSource subscribes it, and holds the bag's times: at the first record's while the
    # subscribers settle, then running with the flight, never back without --loop.
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    from lidar_obstacles.io.bags import BagReader
    from lidar_obstacles.ros import offline

    bag, ns = tmp_path / "bag", "/contract_play_clock"
    offline.simulate(bag, scene="mixed", seed=1, duration=1.0, frame="map",
                     points_per_frame=1000)
    with BagReader(bag) as reader:
        stamps = [r.stamp_ns for r in reader.records()]
    clocks: list = []
    subs = [ros_node.create_subscription(
                Clock, "/clock", clocks.append,
                QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)),
            ros_node.create_subscription(  # (a subscriber: `play` waits less for one)
                PointCloud2, f"{ns}/points", lambda msg: None,
                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))]
    try:
        out, err = _play_to_the_end(ros_node,
                                    _cli("play", bag, "--namespace", ns, "--clock", "100"))
    finally:
        for sub in subs:
            ros_node.destroy_subscription(sub)
    assert json.loads(out) == {"published": len(stamps)}, err
    times = [c.clock.sec * 10**9 + c.clock.nanosec for c in clocks]
    assert len(times) > 50, len(times)
    assert times == sorted(times)
    assert stamps[0] <= times[0] and times[-1] <= stamps[-1], (times[0], times[-1], stamps)
    # it ran with the flight: 0.9 s of the bag's time at 100 Hz
    assert times[-1] - times[0] > 0.8 * (stamps[-1] - stamps[0]), (times[0], times[-1])
    assert len(set(times)) > 30, len(set(times))


@pytest.mark.slow
def test_dem_builder_on_sim_time_publishes_a_dem_while_play_clock_plays(ros_node, tmp_path):
    # The reviewer's case: `dem_builder` with use_sim_time:=true (the launch file's
    # argument for replayed bags) never published a DEM from `play`, nor did anything say
    # why; its publish timer runs on the node's clock, /clock's.
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from test_live_nodes import NS, _spin_until, _start, _stop

    from lidar_obstacles.io.bags import BagReader
    from lidar_obstacles.ros import offline

    bag = tmp_path / "flight"
    offline.simulate(bag, scene="mixed", seed=5, duration=2.5, frame="map",
                     points_per_frame=10_000)
    with BagReader(bag) as reader:
        stamps = [r.stamp_ns for r in reader.records()]
    dems: list = []
    sub = ros_node.create_subscription(
        PointCloud2, f"{NS}/dem", dems.append,
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    dem = _start("lidar_obstacles.scripts.dem_builder", "-p", "use_sim_time:=true",
                 "-p", "dem.publish_rate:=2.0")
    try:
        # up: subscribed to its clouds, and to /clock (use_sim_time)
        assert _spin_until(ros_node, lambda: ros_node.count_subscribers(f"{NS}/points") > 0
                           and ros_node.count_subscribers("/clock") > 0, 60)
        # without --clock: its time stands still, no DEM, and `play` says why, once
        out, err = _play_to_the_end(
            ros_node, _cli("play", bag, "--namespace", NS, "--topics", "/points", "--rate", "5"))
        assert json.loads(out) == {"published": len(stamps) // 2}, err
        assert err.count("use --clock") == 1 and f"{NS}/dem_builder subscribed to /clock" in err
        _spin_until(ros_node, lambda: bool(dems), 1)
        assert not dems
        # with it: the DEM, of the flight's clouds
        out, err = _play_to_the_end(ros_node, _cli("play", bag, "--namespace", NS, "--clock"))
        assert json.loads(out) == {"published": len(stamps)}, err
        assert "use --clock" not in err
        assert _spin_until(ros_node, lambda: bool(dems), 20)
        assert dems[-1].height > 1 and stamps[0] <= dems[-1].header.stamp.sec * 10**9 \
            + dems[-1].header.stamp.nanosec <= stamps[-1]
    finally:
        ros_node.destroy_subscription(sub)
        rc, log = _stop(dem)
    assert rc == 0, log[-3000:]


@pytest.mark.parametrize("points, said", [(50_000, 1), (2000, 0)])
def test_play_says_when_its_clouds_need_the_large_data_profile(tmp_path, points, said):
    bag = tmp_path / "flight"
    sim = _cli("simulate", bag, "--duration", "0.2", "--points", points)
    assert sim.wait(timeout=120) == 0, sim.communicate()[1]
    env = {k: v for k, v in os.environ.items()
           if k not in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")}
    proc = subprocess.run(
        [sys.executable, "-c", "import sys; from pathlib import Path; from lidar_obstacles.ros "
         "import offline; offline.play(Path(sys.argv[1]), settle_s=0.1, wait_s=0.5)", str(bag)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("play: clouds of ") == said, proc.stderr
    if said:
        assert "on /points, over Fast DDS's 512 kB shared-memory segment" in proc.stderr
