"""`evaluate` and `tune` end to end on the shared data and on replayed flights."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import DATA, REPO, data_file
from test_offline import run_cli


def test_evaluate_replay_output_and_report(tmp_path):
    run_cli("simulate", tmp_path / "flight", "--duration", "2", "--seed", "2",
            "--scene", "corridor")
    run_cli("replay", tmp_path / "flight", tmp_path / "out", "--no-dem")
    m = run_cli("evaluate", tmp_path / "out", "--report", tmp_path / "report")
    assert m["kind"] == "replay_bag" and m["clouds"] == 20
    assert m["n_points"] > 100_000
    go = m["ground_object"]
    assert 0.0 <= go["total_error"] <= 1.0 and go["kappa"] > 0.8
    assert m["safety"]["n_wire"] + m["safety"]["n_tower"] > 0
    assert m["safety"]["obstacle_as_ground"] < 0.01
    assert m["dem"]["grid"]["rmse_m"] is not None
    html = (tmp_path / "report" / "report.html").read_text()
    for png in ("confusion", "block_kappa", "classes", "errors", "dem_hillshade"):
        assert (tmp_path / "report" / f"{png}.png").stat().st_size > 5000, png
    assert html.count("data:image/png;base64,") >= 5
    metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert metrics["n_points"] == m["n_points"]


def test_evaluate_a_sensor_frame_bag_through_its_odometry(tmp_path):
    # a labelled flight in the sensor frame: the detector sees it as the node would
    run_cli("simulate", tmp_path / "sensor", "--duration", "1", "--frame", "sensor",
            "--seed", "3")
    params = tmp_path / "odom.yaml"
    params.write_text("/**:\n  ros__parameters:\n    use_odometry: true\n")
    m = run_cli("evaluate", tmp_path / "sensor", "--no-dem", "--params-file", params)
    assert m["kind"] == "labelled_bag" and m["clouds"] == 10
    assert m["ground_object"]["kappa"] > 0.9
    # the same flight simulated in the map frame scores the same
    run_cli("simulate", tmp_path / "map", "--duration", "1", "--seed", "3")
    mapped = run_cli("evaluate", tmp_path / "map", "--no-dem")
    assert m["n_points"] == mapped["n_points"]
    assert m["ground_object"]["kappa"] == pytest.approx(mapped["ground_object"]["kappa"],
                                                        abs=0.01)
    # ... because its clouds were moved into the map frame, and the vehicle is known
    from lidar_obstacles.config import ObstacleDetectorConfig, replace
    from lidar_obstacles.evaluate import load_input

    odom = replace(ObstacleDetectorConfig(), {"use_odometry": True})
    for a, b in zip(load_input(tmp_path / "sensor", cfg=odom).clouds,
                    load_input(tmp_path / "map").clouds, strict=True):
        assert np.allclose(a.xyz.min(axis=0), b.xyz.min(axis=0), atol=0.01)
        assert np.allclose(a.xyz.max(axis=0), b.xyz.max(axis=0), atol=0.01)
        assert a.vehicle is not None and np.allclose(a.vehicle, b.vehicle)


def test_evaluate_las_file():
    m = run_cli("evaluate", data_file("isprs/samp11-utm.laz"), "--no-dem")
    assert m["kind"] == "las" and m["n_points"] == 38010
    assert m["blocks"]["nx"] == 6 and m["blocks"]["n_eligible"] > 10
    assert m["ground_object"]["kappa"] > 0.7
    assert m["latency"]["n"] == 1


@pytest.mark.slow
def test_evaluate_isprs_benchmark():
    folder = DATA / "isprs"
    if not folder.is_dir():
        pytest.skip(f"shared data not present: {folder}")
    res = run_cli("evaluate", "--benchmark", "isprs", folder)
    assert len(res["samples"]) == 15
    assert 0 < res["mean"]["total_error"] < 0.2


@pytest.mark.slow
def test_tune_improves_a_mistuned_start_and_the_yaml_loads_in_the_node(tmp_path):
    src = data_file("isprs/samp51-utm.laz")
    start = tmp_path / "bad.yaml"
    start.write_text("/**:\n  ros__parameters:\n    ground:\n      method: ransac\n"
                     "    ransac:\n      distance_threshold: 0.02\n")
    space = tmp_path / "space.yaml"
    space.write_text("ground.method: [ransac, tin, hybrid]\n"
                     "ransac.distance_threshold: [0.02, 2.0]\n")
    out = tmp_path / "tuned.yaml"
    summary = run_cli("tune", src, "--validate", data_file("isprs/samp52-utm.laz"),
                      "--start", start, "--space", space, "--out", out, "--budget", "90s",
                      "--trials", "6", "--seed", "1")
    assert summary["best_score"] > summary["start_score"] + 0.1
    assert summary["validation"]["best_score"] > summary["validation"]["start_score"]
    assert set(summary["sensitivity"]) <= {"ground.method", "ransac.distance_threshold"}
    # The YAML loads in the live node (which exits on a bad parameter with status 2).
    exe = [sys.executable, "-m", "lidar_obstacles.ros.obstacle_detector", "--ros-args",
           "--params-file", str(out)]
    proc = subprocess.Popen(exe, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        line = ""
        for line in proc.stdout:
            if "subscribed to" in line:
                break
        assert "subscribed to" in line
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_tune_rejects_bad_space(tmp_path):
    space = tmp_path / "space.yaml"
    space.write_text("ransac.distance_threshold: [-1, 2]\n")
    res = subprocess.run([sys.executable, "-m", "lidar_obstacles.cli", "tune",
                          str(data_file("isprs/samp51-utm.laz")), "--space", str(space)],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "ransac.distance_threshold" in res.stderr
    # bad YAML: where and what, in one line (it said only "while parsing a flow sequence")
    from lidar_obstacles.errors import ConfigError
    from lidar_obstacles.tune import search_space

    space.write_text("ransac.distance_threshold: [0.1, 2\n")
    with pytest.raises(ConfigError, match=r"space file .*: line 2, column 1: expected ',' or"):
        search_space(space)


def test_run_detector_stops_at_its_deadline_between_clouds(tmp_path):
    # `tune --budget` holds inside a candidate: the detector stops between two clouds
    import time

    from lidar_obstacles.config import ObstacleDetectorConfig
    from lidar_obstacles.evaluate import load_input, run_detector

    run_cli("simulate", tmp_path / "f", "--duration", "0.3", "--seed", "1")
    inp = load_input(tmp_path / "f")
    with pytest.raises(TimeoutError, match="after 0 of 3 clouds"):
        run_detector(inp, ObstacleDetectorConfig(), deadline=time.monotonic() - 1.0)
    assert len(run_detector(inp, ObstacleDetectorConfig(),
                            deadline=time.monotonic() + 3600.0)) == 3


@pytest.mark.parametrize("points", [[[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]] * 50])
def test_evaluate_report_of_a_cloud_without_area(tmp_path, points):
    # one point, or one spot: the figures are computed and the report says why no maps
    import laspy

    pts = np.array(points)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.classification = np.full(len(pts), 2, np.uint8)
    las.write(str(tmp_path / "spot.las"))
    m = run_cli("evaluate", tmp_path / "spot.las", "--report", tmp_path / "rep")
    assert m["n_points"] == len(pts)
    assert "no maps drawn" in (tmp_path / "rep" / "report.html").read_text()
