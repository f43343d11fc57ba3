"""The contract's `lidar-obstacles` subcommands run as a user runs them: `demo` writes what
it says and says where, `play --loop` plays a bag again and again until Ctrl-C."""
from __future__ import annotations

import json
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


@pytest.fixture(scope="module")
def ros_node():
    rclpy.init()
    node = rclpy.create_node("contract_cli_listener")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


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
