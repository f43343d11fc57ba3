"""Pictures and the HTML report: each PNG is real, sized as stated; the report embeds all."""
from __future__ import annotations

import base64
import json
import struct

import numpy as np
import pytest

from conftest import data_file
from lidar_obstacles import report as R
from lidar_obstacles.core import metrics as M


def png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000
    return struct.unpack(">II", data[16:24])


@pytest.fixture
def cloud():
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(0, 100, 3000), rng.uniform(0, 50, 3000), rng.uniform(0, 20, 3000)]
    ref = rng.choice([2, 5, 6, 14, 15], 3000)
    pred = np.where(rng.random(3000) < 0.8, ref, 2)
    return xyz, ref, pred


def test_pngs(tmp_path, cloud):
    xyz, ref, pred = cloud
    r = M.evaluate_classes(ref, pred, xy=xyz[:, :2])
    p = R.confusion_png(r["confusion"]["matrix"], r["confusion"]["labels"], tmp_path / "c.png")
    assert png_size(p)[0] > 500
    p = R.block_kappa_png(np.array(r["blocks"]["kappa"], float), r["blocks"]["extent"],
                          tmp_path / "b.png")
    assert png_size(p)[0] > 500
    w, _ = png_size(R.cloud_views_png(xyz, ref, tmp_path / "v.png", title="t"))
    assert w == 11 * R.DPI
    w, _ = png_size(R.error_views_png(xyz, ref, pred, tmp_path / "e.png"))
    assert w == 11 * R.DPI
    grid = np.add.outer(np.arange(40.0), np.arange(80.0)) / 10
    grid[5:10, 5:10] = np.nan
    w, h = png_size(R.hillshade_png(grid, 0.5, (1000.0, 2000.0), tmp_path / "h.png"))
    assert h < w  # 40 rows x 80 columns: a wide map
    png_size(R.dem_error_png(grid - grid.mean(), 0.5, (0.0, 0.0), tmp_path / "d.png"))
    assert png_size(R.elbow_png([1, 2, 3, 4], [10, 5, 3, 2.5], 3, tmp_path / "k.png")) == (
        int(6.4 * R.DPI), int(4.2 * R.DPI))
    assert png_size(R.latency_histogram_png(np.linspace(0.01, 0.05, 200), tmp_path / "l.png")) == (
        7 * R.DPI, int(4.2 * R.DPI))
    assert not list(tmp_path.glob(".*tmp"))  # atomic writes leave no temp files


def test_error_categories():
    cat = R.error_categories([2, 2, 5, 5, 14], [2, 5, 2, 6, 14])
    assert cat.tolist() == [0, 1, 2, 3, 0]


def test_report(tmp_path, cloud):
    xyz, ref, pred = cloud
    metrics = {"classes": M.evaluate_classes(ref, pred, xy=xyz[:, :2]),
               "dem": M.grid_errors([1.0, 2.0, 3.0], [1.1, 2.0, 2.9]),
               "latency": M.latency_stats([0.01, 0.02, np.float64(0.03)])}
    images = {"confusion": R.confusion_png(metrics["classes"]["confusion"]["matrix"], M.GROUPS,
                                           tmp_path / "c.png"),
              "latency": R.latency_histogram_png([0.01, 0.02, 0.03], tmp_path / "l.png")}
    path = R.write_report(tmp_path / "out", metrics, images, title="T", notes="n1\nn2")
    text = path.read_text()
    for p in images.values():
        assert "data:image/png;base64," + base64.b64encode(p.read_bytes()).decode() in text
    assert "Type II" in text and "kappa" in text and "rmse_m" in text
    assert f"{100 * metrics['classes']['overall_accuracy']:.2f} %" in text
    loaded = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert loaded == metrics


def test_real_corridor_views(tmp_path, monkeypatch):
    """A power-line corridor over `max_points`: 20 000 of its 38 721 points are drawn, yet
    every wire and tower point, on top in both views (the picture's width is fixed, so its
    size alone said nothing of what was drawn)."""
    from lidar_obstacles.io.las import read_las

    c = read_las(data_file("ahn-corridor/07CZ2_14.laz"))
    xyz = c.xyz[::20]
    ref = c.points["classification"][::20]
    drawn = []
    map_views = R._map_views

    def spy(sub, colours, emphasised, order_top, order_side, *args, **kwargs):
        drawn.append((sub, emphasised, order_top, order_side))
        return map_views(sub, colours, emphasised, order_top, order_side, *args, **kwargs)

    monkeypatch.setattr(R, "_map_views", spy)
    w, h = png_size(R.cloud_views_png(xyz, ref, tmp_path / "v.png", max_points=20_000))
    assert w == 11 * R.DPI and h > 1000
    ((sub, emphasised, order_top, order_side),) = drawn
    thin = np.isin(ref, (14, 15))
    assert len(ref) == 38_721 and thin.sum() == 876 and len(sub) == 20_000
    assert emphasised.sum() == thin.sum()  # not one wire or tower point left out
    assert {tuple(p) for p in sub[emphasised]} == {tuple(p) for p in xyz[thin]}
    for order in (order_top, order_side):  # drawn last: over the ground and the trees
        assert np.array_equal(np.sort(order), np.arange(len(sub)))
        assert emphasised[order][-876:].all()


def test_report_files_get_the_mode_open_would_give(tmp_path):
    # written through a 0o600 temporary file, renamed: the mode must still follow the umask
    import os

    old = os.umask(0o022)
    try:
        R.write_report(tmp_path / "r", {"section": {"a": 1}}, {})
    finally:
        os.umask(old)
    for name in ("report.html", "metrics.json"):
        assert (tmp_path / "r" / name).stat().st_mode & 0o777 == 0o644


def test_the_markers_and_the_pictures_colour_each_class_alike():
    # wires were yellow in RViz and cyan in the reports; then two tables kept in step
    from lidar_obstacles.core.classes import CLASS_COLOURS, CLASS_NAMES

    assert set(CLASS_COLOURS) == set(CLASS_NAMES)
    for code, rgb in CLASS_COLOURS.items():
        hexcode = R.CLASS_STYLE[code][1]
        assert hexcode == "#" + "".join(f"{round(255 * c):02x}" for c in rgb), code
