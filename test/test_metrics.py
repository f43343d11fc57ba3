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
    assert r["mae_m"] == pytest.approx(0.5) and r["max_abs_m"] == pytest.approx(1.0)
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
    # linear interpolation between the 95th and 96th of 100 values, and so on
    assert r["p95_s"] == pytest.approx(0.09505) and r["p99_s"] == pytest.approx(0.09901)
    assert r["mean_s"] == pytest.approx(0.0505)
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


def test_a_reference_of_ground_and_object_only_judges_no_object_class():
    # ISPRS labels objects 0: a tree or a roof found was "wrong" against it, and samp11
    # scored overall accuracy 0.55, kappa 0.31, for total error 8.5 %, kappa 0.83
    from lidar_obstacles.report import error_categories

    ref = np.array([2, 2, 2, 0, 0, 0, 1, 0])
    pred = np.array([2, 2, 5, 5, 6, 2, 14, 1])
    r = M.evaluate_classes(ref, pred)
    assert r["reference_classes_objects"] is False
    assert r["merged_into_other"] == ["vegetation", "building", "wire", "tower"]
    assert r["overall_accuracy"] == pytest.approx(1.0 - r["ground_object"]["total_error"])
    assert r["kappa"] == pytest.approx(r["ground_object"]["kappa"])
    assert error_categories(ref, pred).tolist() == [0, 0, 1, 0, 0, 2, 0, 0]
    # one classed object in the reference, and the classes are judged again
    ref[3] = 5
    r = M.evaluate_classes(ref, pred)
    assert r["reference_classes_objects"] is True and r["per_class"]["vegetation"][
        "producers_accuracy"] == 1.0
    assert error_categories(ref, pred).tolist() == [0, 0, 1, 0, 3, 2, 3, 0]
    assert r["merged_into_other"] == []


def test_a_reference_without_vegetation_judges_no_vegetation_found():
    # AHN4: 1 other (mostly vegetation), 2 ground, 6 building. Its trees found as
    # vegetation were 21.8 % of the tile "of the wrong class".
    from lidar_obstacles.report import error_categories

    ref = np.array([2, 2, 1, 1, 1, 6, 6, 1])
    pred = np.array([2, 5, 5, 3, 6, 6, 5, 14])
    r = M.evaluate_classes(ref, pred)
    assert r["reference_classes_objects"] is True and r["merged_into_other"] == ["vegetation"]
    other = r["per_class"]["other"]
    assert (other["reference_count"], other["predicted_count"]) == (4, 4)
    assert r["per_class"]["vegetation"]["predicted_count"] == 0
    # a building on "other" and a building called vegetation stay wrong; a wire too
    assert r["per_class"]["building"]["users_accuracy"] == pytest.approx(0.5)
    assert r["per_class"]["building"]["producers_accuracy"] == pytest.approx(0.5)
    assert r["per_class"]["wire"]["predicted_count"] == 1
    assert error_categories(ref, pred).tolist() == [0, 1, 0, 0, 3, 0, 3, 3]
    # with no "other" in the reference, vegetation found on a building is no other point
    r = M.evaluate_classes(np.array([2, 6, 6]), np.array([2, 5, 6]))
    assert r["merged_into_other"] == [] and r["per_class"]["vegetation"]["predicted_count"] == 1


def test_type_i_and_type_ii_are_not_interchangeable():
    # 4 reference ground, 6 reference object; 1 ground rejected (Type I error), 3 objects
    # accepted as ground (Type II error). Unequal on purpose: with 1 and 1 of 5 and 5 (the
    # hand test above) a swap of the two figures, or of their denominators, goes unseen.
    ref = [2, 2, 2, 2, 6, 6, 6, 5, 5, 1]
    pred = [2, 2, 2, 6, 2, 2, 2, 5, 5, 1]
    go = M.evaluate_classes(ref, pred)["ground_object"]
    assert (go["n_ground"], go["n_object"]) == (4, 6)
    assert go["type_i"] == pytest.approx(1 / 4)
    assert go["type_ii"] == pytest.approx(3 / 6)
    assert go["total_error"] == pytest.approx(4 / 10)
    # rows predicted, columns reference: [[g->g, o->g], [g->o, o->o]]
    assert go["matrix"] == [[3, 3], [1, 3]]
    # P_o = 6/10; P_e = (6*4 + 4*6)/100 = .48
    assert go["kappa"] == pytest.approx((0.6 - 0.48) / (1 - 0.48))


def test_blocks_are_numbered_rows_south_to_north_on_a_non_square_extent():
    # nx = 2 columns over x in [5, 15], ny = 3 rows over y in [10, 50]: the extent is 4x
    # taller than wide, so a row index scaled by the x span, or blocks numbered column-
    # major, puts the points in other blocks. Block (column ix, row iy) holds 1 + ix + 2 iy
    # points, all ground and found, except the north-east one, a 2 x 2 table of 10 points
    # with unequal marginals (rows predicted, columns reference):
    #   predicted ground:  5 (ground)  2 (object)
    #   predicted object:  1           2
    # P_o = 7/10; P_e = (7*6 + 3*4)/100 = .54; kappa = .16/.46
    xs, ys = (5.0, 15.0), (10.0, 30.0, 50.0)
    xy, ref, pred = [], [], []
    for iy in range(3):
        for ix in range(2):
            if (ix, iy) == (1, 2):
                r = [True] * 6 + [False] * 4
                p = [True] * 5 + [False] + [True] * 2 + [False] * 2
            else:
                r = p = [True] * (1 + ix + 2 * iy)
            xy += [(xs[ix], ys[iy])] * len(r)
            ref += r
            pred += p
    b = M.block_kappa(np.array(xy), np.array(ref), np.array(pred), blocks="2x3")
    assert b["extent"] == [5.0, 15.0, 10.0, 50.0]
    assert b["n_points"] == [[1, 2], [3, 4], [5, 10]]  # row 0 = south
    assert b["kappa"][:2] == [[None, None], [None, None]]  # all ground: not eligible
    assert b["kappa"][2][0] is None
    assert b["kappa"][2][1] == pytest.approx(0.16 / 0.46)
    assert b["n_eligible"] == 1 and b["mean_kappa"] == pytest.approx(0.16 / 0.46)
    assert b["share_kappa_gt_0_6"] == 0.0


def test_grid_values_at_is_exact_on_a_plane_with_origin_and_resolution():
    # Bilinear interpolation reproduces a plane exactly, so any weight given to the wrong
    # corner, or a wrong origin, resolution or half-cell shift, shows. Cell (r, c) has its
    # centre at (100 + 2 (c + 0.5), 200 + 2 (r + 0.5)).
    res, origin = 2.0, (100.0, 200.0)

    def plane(x, y):
        return 3.0 + 0.5 * (x - 100.0) - 0.25 * (y - 200.0)

    cx = origin[0] + (np.arange(4) + 0.5) * res
    cy = origin[1] + (np.arange(3) + 0.5) * res
    grid = plane(cx[None, :], cy[:, None])
    pts = np.array([[101.5, 202.5],   # fc = 0.25, fr = 0.75 in the first cell square
                    [104.9, 201.2], [106.9, 204.9], [101.0, 201.0]])
    z = M.grid_values_at(grid, pts, resolution=res, origin=origin)
    np.testing.assert_allclose(z, plane(pts[:, 0], pts[:, 1]))
    # outside the hull of the cell centres (x < 101 or y > 205): NaN
    assert np.isnan(M.grid_values_at(grid, [[100.9, 202.0], [103.0, 205.1]], resolution=res,
                                     origin=origin)).all()


def test_by_code_counts_each_pair_of_reference_and_predicted_codes():
    """`by_code`: the code-level cross table the groups hide (class 26, a crane, is `other`
    like 1 and 7; here half of it became unclassified, half vegetation)."""
    ref = [26, 26, 26, 26, 2, 2, 1, 7]
    pred = [1, 1, 5, 5, 2, 2, 1, 1]
    by_code = M.evaluate_classes(ref, pred)["by_code"]
    assert by_code == {"1": {"1": 1}, "2": {"2": 2}, "7": {"1": 1}, "26": {"1": 2, "5": 2}}
    assert sum(n for row in by_code.values() for n in row.values()) == len(ref)
    assert json.loads(json.dumps(by_code)) == by_code


def test_shield_wires_and_insulators_count_with_the_wires_and_towers():
    # a reference with guard wires (13) and insulators (16) put in ground: safety said 0
    ref = np.array([2] * 50 + [13] * 10 + [14] * 10 + [16] * 4 + [15] * 6)
    pred = np.array([2] * 50 + [2] * 10 + [14] * 10 + [2] * 4 + [15] * 6)
    r = M.evaluate_classes(ref, pred)
    assert r["safety"] == {"n_wire": 20, "n_tower": 10, "wire_as_ground": 0.5,
                           "tower_as_ground": 0.4, "obstacle_as_ground": 14 / 30}
    # and a shield wire found as a wire (14) is the right class
    r = M.evaluate_classes(ref, np.where(ref == 13, 14, np.where(ref == 16, 15, ref)))
    assert r["overall_accuracy"] == 1.0 and r["per_class"]["wire"]["reference_count"] == 20
