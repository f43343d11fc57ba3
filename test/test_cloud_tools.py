"""`lidar-obstacles simplify` and `features` on LAS/LAZ files and bags, and the detector's
`obstacle_edges` in `replay`: outputs keep every field, land atomically, and bad input is
one line with exit status 2."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import data_file
from lidar_obstacles.io.bags import BagReader
from lidar_obstacles.io.las import read_las
from test_offline import cli_subprocess, clouds, run_cli

SAMPLE = "isprs/samp71-utm.laz"  # small (~15k points), sparse Vaihingen terrain


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("tools") / "flight"
    run_cli("simulate", out, "--duration", "0.3", "--seed", "4", "--points", "10000")
    return out


def _count(bag, topic: str) -> int:
    with BagReader(bag) as reader:
        return reader.count([topic])


def _rows(points: np.ndarray) -> set[tuple]:
    return set(map(tuple, np.column_stack([points[n] for n in ("x", "y", "z")]).round(3)))


def test_simplify_las_keeps_a_share_of_the_points_with_every_field(tmp_path):
    src = data_file(SAMPLE)
    out = tmp_path / "simple.laz"
    summary = run_cli("simplify", src, out)
    full, kept = read_las(src), read_las(out)
    assert summary["points_out"] == len(kept.points) > 0
    assert 0.5 < summary["reduction"] < 0.95, summary
    assert kept.points.dtype == full.points.dtype and kept.epsg == full.epsg
    assert _rows(kept.points) <= _rows(full.points)  # a subset, nothing moved
    assert summary["r"] > 0.9  # the kept points still draw the terrain (0.980)
    assert [p.name for p in tmp_path.iterdir()] == ["simple.laz"]  # no partial file left


def test_simplify_paper_method_from_a_params_file(tmp_path):
    src = data_file(SAMPLE)
    params = tmp_path / "p.yaml"
    params.write_text("cloud_simplifier:\n  ros__parameters:\n    simplify:\n"
                      "      method: normal_cluster\n      restarts: 2\n")
    summary = run_cli("simplify", src, tmp_path / "paper.las", "--params-file", params)
    assert summary["method"] == "normal_cluster" and summary["k"] >= 1
    assert summary["points_out"] == len(read_las(tmp_path / "paper.las").points)


def test_simplify_and_features_of_a_bag(sim_bag, tmp_path):
    s = run_cli("simplify", sim_bag, tmp_path / "simple")
    f = run_cli("features", sim_bag, tmp_path / "feat")
    inputs = clouds(sim_bag, "/points")
    for summary, topic, bag in ((s, "/points_simplified", tmp_path / "simple"),
                                (f, "/points_features", tmp_path / "feat")):
        outs = clouds(bag, topic)
        assert summary["messages"] == len(inputs) == len(outs) == 3
        assert summary["points_out"] == sum(len(o) for o in outs)
        for cin, cout in zip(inputs, outs):
            assert cout.dtype.names == cin.dtype.names  # every field kept
            assert _rows(cout) <= _rows(cin)
        assert _count(bag, "/odom") == _count(sim_bag, "/odom") > 0  # copied along
    assert 0 < s["points_out"] < s["points_in"]
    assert 0 < f["points_out"] < f["points_in"]  # buildings and towers have edges


@pytest.mark.parametrize("command, topic", [("simplify", "/points_simplified"),
                                            ("features", "/points_features")])
def test_a_recorded_output_topic_is_replaced_not_mixed_in(command, topic, sim_bag, tmp_path):
    """A flight recorded beside a live cloud_simplifier holds its /points_simplified: the
    new clouds were written beside the recorded ones, each cloud twice."""
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter

    recorded = tmp_path / "recorded"
    with BagReader(sim_bag) as reader, BagWriter(recorded) as bag:
        for name in ("/points", topic):
            bag.add_topic(name, POINTCLOUD2)
        for rec in reader.records(["/points"]):
            for name in ("/points", topic):
                bag.write(name, rec.stamp_ns, rec.raw)
    summary = run_cli(command, recorded, tmp_path / "out", "--topic", "/points")
    assert _count(tmp_path / "out", topic) == summary["messages"] == 3


def test_simplify_counts_malformed_clouds_by_kind_and_keeps_the_last_error(sim_bag, tmp_path):
    from test_evaluate_cli import _cut_short

    _cut_short(sim_bag, tmp_path / "cut", {0, 2})
    res = cli_subprocess("simplify", tmp_path / "cut", tmp_path / "simple")
    assert res.returncode == 2 and not (tmp_path / "simple").exists()  # (by default: stop)
    assert res.stderr.startswith("lidar-obstacles simplify: error: cloud 1 on /points (stamp ")
    s = run_cli("simplify", tmp_path / "cut", tmp_path / "simple", "--skip-malformed")
    assert s["messages"] == 1 and s["rejected"] == 2
    assert s["reject_reasons"] == {"data has N bytes, expected row_step N * height N = N": 2}
    assert s["last_reject"].startswith("data has ") and s["last_reject"][9].isdigit()


def test_stray_points_are_no_features_and_raise_no_warnings(sim_bag, tmp_path):
    """50 points of each cloud at (1e30, 1e30, 1e30) m (a bad coordinate): left out of the
    feature search, quietly (numpy overflowed on them), in a bag and in a whole survey."""
    import warnings

    from lidar_obstacles.config import FeaturesConfig
    from lidar_obstacles.io.bags import POINTCLOUD2, BagWriter, typestore
    from lidar_obstacles.io.pointcloud2 import read_points
    from lidar_obstacles.ros.cloud_tools import tiled_features

    bag = tmp_path / "strays"
    with BagReader(sim_bag) as reader, BagWriter(bag) as out:
        out.add_topic("/points", POINTCLOUD2)
        for rec in reader.records(["/points"]):
            msg = reader.deserialize(rec)
            points = np.array(read_points(msg))
            for axis in "xyz":
                points[axis][:50] = 1e30
            msg.data = np.frombuffer(points.tobytes(), np.uint8)
            out.write("/points", rec.stamp_ns, bytes(typestore().serialize_cdr(msg, POINTCLOUD2)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        summary = run_cli("features", bag, tmp_path / "feat")
        assert summary["points_out"] > 0
        assert all((c["z"] < 1e3).all() for c in clouds(tmp_path / "feat", "/points_features"))
        survey = read_las(data_file(SAMPLE)).xyz
        survey[:5] = 1e30
        feature = tiled_features(survey, cfg=FeaturesConfig(), rng=np.random.default_rng(0))
        assert not feature[:5].any() and feature[5:].any()


def test_features_of_a_las_file(tmp_path):
    src = data_file(SAMPLE)
    summary = run_cli("features", src, tmp_path / "edges.laz")
    kept, full = read_las(tmp_path / "edges.laz"), read_las(src)
    assert summary["points_out"] == len(kept.points)
    assert 0.005 < summary["share"] < 0.6, summary
    assert _rows(kept.points) <= _rows(full.points)


def test_a_las_file_of_no_points_gives_an_empty_result_or_one_line(tmp_path, capsys):
    """`features` of a few points finds none and writes a LAS file of 0 points, which is
    valid: `simplify` and `features` take it (0 points in, a LAS/LAZ of 0 points out, the
    header kept); `evaluate` and `las2bag` can do nothing with it and say so in one line
    with exit status 2 (no traceback, no output)."""
    import laspy

    from lidar_obstacles.cli import main

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500_000.0, 5_000_000.0, 0.0]
    few = laspy.LasData(header)
    few.x, few.y, few.z = 500_000.0 + np.arange(5.0), 5_000_000.0 + np.zeros(5), np.ones(5)
    few.write(tmp_path / "few.las")
    summary = run_cli("features", tmp_path / "few.las", tmp_path / "none.las")
    assert (summary["points_in"], summary["points_out"]) == (5, 0)
    none = tmp_path / "none.las"
    for command, name in (("simplify", "s.laz"), ("features", "f.las")):
        summary = run_cli(command, none, tmp_path / name)
        assert (summary["points_in"], summary["points_out"]) == (0, 0), summary
        assert summary.get("reduction", summary.get("share")) == 0.0
        out = laspy.read(tmp_path / name)
        assert len(out.points) == 0 and out.header.point_format.id == 3
        assert list(out.header.offsets) == list(header.offsets)
    assert len(read_las(none, allow_empty=True).points) == 0
    capsys.readouterr()
    for args in (("evaluate", none), ("las2bag", none, tmp_path / "bag")):
        assert main([str(a) for a in args]) == 2
        err = capsys.readouterr().err
        assert err.splitlines() == [f"lidar-obstacles {args[0]}: error: LAS file has no "
                                    f"points: {none}"], err
    assert not (tmp_path / "bag").exists()


def test_tiled_features_match_the_whole_cloud_inside_the_tiles():
    """Tiles with a margin give each point the neighbours it has in the whole survey: boxes
    across the 100 m tile borders get the same feature points as in one piece."""
    from lidar_obstacles.config import FeaturesConfig
    from lidar_obstacles.core.features import gaussian_map_features
    from lidar_obstacles.ros import cloud_tools
    from test_features import _box

    rng = np.random.default_rng(1)
    corners = [(0, 0), (98.5, 0), (0, 98.7), (98.6, 98.4), (150, 150), (199, 40)]
    xyz = np.concatenate([_box(rng, noise=0.005)[0] + (x, y, 0) for x, y in corners])
    cfg = FeaturesConfig()
    whole = gaussian_map_features(xyz, cfg=cfg, rng=np.random.default_rng(0)).feature
    tiled = cloud_tools.tiled_features(xyz, cfg=cfg, rng=np.random.default_rng(0))
    assert whole.sum() > 100  # the boxes' edges and corners
    assert (whole == tiled).mean() > 0.97, (whole == tiled).mean()


@pytest.mark.parametrize("args, expected", [
    (("simplify", "{src}", "{tmp}/out.bag"), "needs a .las or .laz output"),
    (("features", "{tmp}/missing.laz", "{tmp}/out.laz"), "not found"),
    (("simplify", "{tmp}/nobag", "{tmp}/out"), "nobag"),
    (("simplify", "{tmp}/nonexistent_path", "{tmp}/o.laz"), "input not found: "),
    (("simplify", "{src}", "{tmp}/notes.laz"), "notes.laz exists and is not a LAS/LAZ file"),
])
def test_bad_input_is_one_line_and_exit_2(args, expected, tmp_path):
    src = data_file(SAMPLE)
    (tmp_path / "notes.laz").write_text("precious\n")  # not a LAS/LAZ file: never replaced
    proc = cli_subprocess(*[a.format(src=src, tmp=tmp_path) for a in args])
    assert proc.returncode == 2, proc.stderr
    assert (tmp_path / "notes.laz").read_text() == "precious\n"
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and expected in lines[0], proc.stderr
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())


class _Bar:
    """A progress bar that records what it is told."""

    def __init__(self, iterable, total, desc, unit="msg"):
        self.total, self.desc, self.unit, self.n, self.postfix = total, desc, unit, 0, []

    def update(self, n=1):
        self.n += n

    def set_postfix_str(self, text, refresh=True):
        self.postfix.append(text)

    def close(self):
        pass


def test_long_survey_commands_show_progress_inside_a_tile_and_a_step(tmp_path, monkeypatch):
    """`features` of a 50 m survey sat at "0/1 tile" for 19 s, `simplify` of a corridor
    tile showed no bar for 18 s: the bars now count points (margins included) and name
    the step under way."""
    from lidar_obstacles.ros import cloud_tools

    bars: list[_Bar] = []
    monkeypatch.setattr(cloud_tools, "_progress", lambda *a, **k: bars.append(_Bar(*a, **k))
                        or bars[-1])
    src = data_file("isprs/samp71-utm.laz")
    run_cli("features", src, tmp_path / "f.laz")
    (bar,) = bars
    assert (bar.desc, bar.unit) == ("features", "pt") and bar.n == bar.total >= 7000
    run_cli("simplify", src, tmp_path / "s.laz")
    bar = bars[-1]
    assert (bar.desc, bar.n, bar.total) == ("simplify", 4, 4)
    assert bar.postfix == ["normals", "k-means", "selection", "validation"]
