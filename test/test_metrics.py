"""Known-answer tests of lidar_obstacles.core.metrics (hand computations in comments)."""
from __future__ import annotations

import json
import re
import warnings

import numpy as np
import pytest

from conftest import REPO, data_file
from lidar_obstacles.core import metrics as M
from lidar_obstacles.errors import CloudFormatError, ConfigError


def test_groups():
    g = M.group_of([2, 8, 9, 11, 3, 4, 5, 6, 14, 15, 1, 7, 0, 26])
    assert [M.GROUPS[i] for i in g] == ["ground"] * 4 + ["vegetation"] * 3 + [
        "building", "wire", "tower"] + ["other"] * 4


def test_readme_lists_every_top_level_key_of_the_metrics():
    readme = (REPO / "README.md").read_text()
    table = readme.split("### `evaluate` JSON keys", 1)[1].split("\n## ", 1)[0]
    listed = {name.split(".")[0] for row in table.splitlines() if row.startswith("| `")
              for name in re.findall(r"`([^`]+)`", row.split(" | ")[0])}
    assert set(M.evaluate_classes([2, 5, 6], [2, 5, 5])) <= listed


def test_hand_confusion_and_kappa():
    # 10 points.  reference: 5 ground (2), 3 veg (5), 2 building (6)
    ref = [2, 2, 2, 2, 2, 5, 5, 5, 6, 6]
    pred = [2, 2, 2, 2, 5, 5, 5, 2, 6, 5]
    # rows predicted, columns reference (ground, veg, building):
    #   pred ground:    4  1  0   -> Q_g+ = 5
    #   pred veg:       1  2  1   -> Q_v+ = 4
    #   pred building:  0  0  1   -> Q_b+ = 1
    #   column totals   5  3  2
    # P_o = 7/10 ; P_e = (5*5 + 4*3 + 1*2)/100 = 0.39 ; kappa = 0.31/0.61
    r = M.evaluate_classes(ref, pred)
    m = np.array(r["confusion"]["matrix"])
    assert m[:3, :3].tolist() == [[4, 1, 0], [1, 2, 1], [0, 0, 1]]
    assert r["overall_accuracy"] == pytest.approx(0.7)
    assert r["kappa"] == pytest.approx(0.31 / 0.61)
    pc = r["per_class"]
    assert pc["ground"]["users_accuracy"] == pytest.approx(4 / 5)
    assert pc["vegetation"]["users_accuracy"] == pytest.approx(2 / 4)
    assert pc["vegetation"]["producers_accuracy"] == pytest.approx(2 / 3)
    assert pc["building"]["users_accuracy"] == pytest.approx(1.0)
    assert pc["building"]["producers_accuracy"] == pytest.approx(0.5)
    # conditional kappa, vegetation: num = 10*2 - 4*3 = 8;
    # user's den = 10*4 - 12 = 28, producer's den = 10*3 - 12 = 18
    assert pc["vegetation"]["users_kappa"] == pytest.approx(8 / 28)
    assert pc["vegetation"]["producers_kappa"] == pytest.approx(8 / 18)
    assert pc["wire"]["users_accuracy"] is None
    # ground/object: Type I = 1 of 5 ground rejected; Type II = 1 of 5 objects as ground
    go = r["ground_object"]
    assert go["type_i"] == pytest.approx(0.2) and go["type_ii"] == pytest.approx(0.2)
    assert go["total_error"] == pytest.approx(0.2)
    # 2x2: [[4,1],[1,4]] -> P_o .8, P_e .5, kappa .6
    assert go["kappa"] == pytest.approx(0.6)
    json.dumps(r, allow_nan=False)


def test_against_sklearn_kappa():
    from sklearn.metrics import cohen_kappa_score

    rng = np.random.default_rng(0)
    ref = rng.choice([2, 5, 6, 14, 15, 1], 5000)
    pred = np.where(rng.random(5000) < 0.7, ref, rng.choice([2, 5, 6, 1], 5000))
    r = M.evaluate_classes(ref, pred)
    assert r["kappa"] == pytest.approx(cohen_kappa_score(M.group_of(ref), M.group_of(pred)))


def test_perfect_and_chance():
    rng = np.random.default_rng(1)
    ref = rng.choice([2, 5, 6], 20000)
    assert M.evaluate_classes(ref, ref)["kappa"] == pytest.approx(1.0)
    pred = rng.choice([2, 5, 6], 20000)
    assert abs(M.evaluate_classes(ref, pred)["kappa"]) < 0.03


def test_degenerate_one_class_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = M.evaluate_classes([2, 2, 2], [2, 2, 2])
        assert r["kappa"] is None and r["overall_accuracy"] == 1.0
        assert r["ground_object"]["type_ii"] is None
        assert r["safety"]["wire_as_ground"] is None
        json.dumps(r, allow_nan=False)
        b = M.block_kappa(np.zeros((3, 2)), np.ones(3, bool), np.ones(3, bool))
        assert b["n_eligible"] == 0 and b["share_kappa_gt_0_8"] is None


def test_bad_input():
    with pytest.raises(CloudFormatError):
        M.evaluate_classes([2, 2], [2])
    with pytest.raises(CloudFormatError):
        M.evaluate_classes([], [])
    with pytest.raises(CloudFormatError):
        M.evaluate_classes([2.5], [2])
    with pytest.raises(ConfigError):
        M.parse_blocks("6by6")
    assert M.parse_blocks("4x3") == (4, 3)


def test_blocks_eligibility():
    # 2x1 blocks: left block x<1 has 10 ground + 10 object (eligible);
    # right block has 99 ground + 1 object (1 % < 5 %: not eligible)
    xy = np.r_[np.c_[np.full(20, 0.2), np.arange(20.0) / 20],
               np.c_[np.full(100, 1.8), np.arange(100.0) / 100]]
    ref = np.r_[np.ones(10, bool), np.zeros(10, bool), np.ones(99, bool), np.zeros(1, bool)]
    pred = ref.copy()
    pred[0] = False  # one ground rejected in the left block: [[9,0],[1,10]]
    b = M.block_kappa(xy, ref, pred, blocks=(2, 1))
    # P_o = .95, P_e = (9*10 + 11*10)/400 = .5, kappa = .9
    assert b["kappa"][0][0] == pytest.approx(0.9)
    assert b["kappa"][0][1] is None
    assert b["n_eligible"] == 1 and b["share_kappa_gt_0_8"] == 1.0
    assert b["n_points"] == [[20, 100]]


def test_safety():
    r = M.evaluate_classes([14, 14, 14, 14, 15, 15], [2, 14, 14, 14, 2, 2])
    assert r["safety"]["wire_as_ground"] == pytest.approx(0.25)
    assert r["safety"]["tower_as_ground"] == pytest.approx(1.0)
    assert r["safety"]["obstacle_as_ground"] == pytest.approx(0.5)


def test_grid_errors_nan():
    ref = np.array([[1.0, 2.0], [np.nan, 4.0]])
    est = np.array([[2.0, 2.0], [5.0, np.nan]])
    r = M.grid_errors(ref, est)  # compared: (1,2) and (2,2) -> errors 1, 0
    assert r["n"] == 2 and r["rmse_m"] == pytest.approx(np.sqrt(0.5))
    assert r["bias_m"] == pytest.approx(0.5)
    # SS_tot about mean 1.5 = 0.5, SS_res = 1 -> r2 = -1
    assert r["r2"] == pytest.approx(-1.0)
    assert M.grid_errors([np.nan], [1.0])["rmse_m"] is None
    assert M.raster_correlation(ref, 2 * ref + 1) == pytest.approx(1.0)
    assert M.raster_correlation([1.0, 1.0], [1.0, 2.0]) is None


def test_grid_values_at():
    grid = np.arange(6.0).reshape(2, 3)  # z = c + 3 r, centres at (c+.5, r+.5)
    z = M.grid_values_at(grid, [[1.0, 1.0], [0.5, 0.5], [9.0, 9.0]], resolution=1.0,
                         origin=(0.0, 0.0))
    assert z[0] == pytest.approx(0.5 + 1.5) and z[1] == pytest.approx(0.0) and np.isnan(z[2])


def test_latency():
    r = M.latency_stats(np.arange(1, 101) / 1000.0)
    assert r["n"] == 100 and r["max_s"] == pytest.approx(0.1)
    assert r["p50_s"] == pytest.approx(0.0505)
    assert M.latency_stats([])["p95_s"] is None


def test_real_isprs_perfect_and_flipped():
    from lidar_obstacles.io.las import read_las

    cloud = read_las(data_file("isprs/samp11-utm.laz"))
    ref = cloud.points["classification"]
    pred = ref.copy()
    pred[::10] = np.where(ref[::10] == 2, 0, 2)  # flip every tenth point
    r = M.evaluate_classes(ref, pred, xy=cloud.xyz[:, :2], blocks="6x6")
    assert r["ground_object"]["total_error"] == pytest.approx(np.ceil(ref.size / 10) / ref.size)
    assert r["blocks"]["n_blocks"] == 36 and r["blocks"]["n_eligible"] > 0
    json.dumps(r, allow_nan=False)
