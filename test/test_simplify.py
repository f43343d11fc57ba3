"""Simplification by K-means++ on normals (core.simplify): synthetic cases with known answers."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lidar_obstacles.config import SimplifyConfig
from lidar_obstacles.core.simplify import (cluster_quotas, normal_space_sample, pca_normals,
                                           simplify, tin_raster_correlation, voxel_sample)
from lidar_obstacles.errors import CloudFormatError

FAST = SimplifyConfig(restarts=2, sample_size=2000, max_k=6, validate=True)


def _plane(rng, n=2000, slope=(0.0, 0.0), size=10.0, noise=0.0):
    xy = rng.uniform(0, size, (n, 2))
    z = slope[0] * xy[:, 0] + slope[1] * xy[:, 1] + rng.normal(0, noise, n) if noise else (
        slope[0] * xy[:, 0] + slope[1] * xy[:, 1])
    return np.column_stack([xy, z])


def _gable_and_ground(rng, n_roof=3000, n_ground=3000):
    """Ground (z = 0) around a 10 x 10 m gable roof (ridge along y at x = 15, 45 degrees,
    eaves at 5 m): three face orientations, normals (0,0,1) and (+-1,0,1)/sqrt(2)."""
    ground = np.column_stack([rng.uniform(0, 30, n_ground), rng.uniform(0, 30, n_ground),
                              np.zeros(n_ground)])
    ground = ground[~((np.abs(ground[:, 0] - 15) < 5) & (np.abs(ground[:, 1] - 15) < 5))]
    x = rng.uniform(10, 20, n_roof)
    y = rng.uniform(10, 20, n_roof)
    roof = np.column_stack([x, y, 10.0 - np.abs(x - 15.0)])
    return np.vstack([ground, roof])


# --------------------------------------------------------------------------- normals


def test_normals_of_a_plane_point_up():
    n = pca_normals(_plane(np.random.default_rng(0)), neighbours=10)
    assert n.shape == (2000, 3) and n.dtype == np.float64
    assert np.linalg.norm(n, axis=1) == pytest.approx(1.0)
    assert n[:, 2] == pytest.approx(1.0, abs=1e-9)  # oriented z >= 0, not +-1


def test_normals_of_a_tilted_plane():
    xyz = _plane(np.random.default_rng(1), slope=(0.5, -0.25), noise=0.002)
    expected = np.array([-0.5, 0.25, 1.0]) / np.linalg.norm([-0.5, 0.25, 1.0])
    n = pca_normals(xyz, neighbours=12)
    assert np.median(n @ expected) > 0.999
    assert np.all(n[:, 2] >= 0)


def test_normals_of_a_box_faces():
    rng = np.random.default_rng(2)
    u, v = rng.uniform(0.05, 0.95, (2, 600))
    faces = {(1, 0, 0): np.column_stack([np.ones(600), u, v]),
             (0, 1, 0): np.column_stack([u, np.ones(600), v]),
             (0, 0, 1): np.column_stack([u, v, np.ones(600)])}
    xyz = np.vstack(list(faces.values()))
    n = pca_normals(xyz, neighbours=8)
    for i, axis in enumerate(faces):
        face = n[i * 600:(i + 1) * 600]
        # interior points of each face: |n . axis| ~ 1 (edges mix two faces)
        assert np.median(np.abs(face @ np.array(axis, dtype=float))) > 0.999


def test_pca_normals_rejects_nan():
    with pytest.raises(CloudFormatError):
        pca_normals(np.array([[0.0, 0.0, np.nan]] * 5), neighbours=3)


# --------------------------------------------------------------------------- validation


def test_tin_raster_correlation_full_set_is_one_and_bad_subset_lower():
    rng = np.random.default_rng(3)
    xyz = _gable_and_ground(rng)
    assert tin_raster_correlation(xyz, xyz, cell=0.5) == pytest.approx(1.0)
    roof_only = xyz[xyz[:, 2] > 0]  # loses the ground: the TIN spans only the roof
    ground_and_one_slope = xyz[(xyz[:, 2] == 0) | (xyz[:, 0] < 15)]
    r_bad = tin_raster_correlation(ground_and_one_slope, xyz, cell=0.5)
    assert r_bad < 0.95
    assert np.isnan(tin_raster_correlation(roof_only[:2], xyz, cell=0.5))  # no surface
    even = xyz[voxel_sample(xyz, len(xyz) // 5, rng)]
    assert tin_raster_correlation(even, xyz, cell=0.5) > r_bad


@pytest.mark.parametrize("z", [0.0, 12.5, 100.3])
def test_tin_raster_correlation_of_a_flat_cloud_is_nan(z):
    # both rasters are constant, but for the TIN's rounding (4e-14 m at 100.3 m): the r of
    # that noise came out as any number (0.70 at 100.3 m, -0.003 at 12.5 m)
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 50, (3000, 2)), np.full(3000, z)])
    assert np.isnan(tin_raster_correlation(xyz[::5], xyz, cell=1.0))
    assert np.isnan(simplify(xyz, cfg=FAST).r)  # (FAST validates)


# --------------------------------------------------------------------------- selection


def test_cluster_quotas_sum_and_keep_every_cluster():
    q = cluster_quotas(np.array([9000, 500, 30, 0]), 900)
    assert q.sum() == 900 and q[3] == 0 and np.all(q[:3] >= 1)
    assert q[0] == pytest.approx(900 * 9000 / 9530, abs=1)


def test_voxel_sample_exact_count_and_even():
    rng = np.random.default_rng(4)
    xyz = _plane(rng, n=5000, size=10.0)
    keep = voxel_sample(xyz, 500, rng)
    assert keep.sum() == 500
    # even coverage: every 2 x 2 m block keeps ~ 20 points (a clustered pick would not)
    counts = np.bincount((np.floor(xyz[keep, 0] / 2) * 5 + np.floor(xyz[keep, 1] / 2))
                         .astype(int), minlength=25)
    assert counts.min() >= 10


def test_gable_roof_gives_one_cluster_per_face_and_normal_space_keeps_them():
    rng = np.random.default_rng(5)
    xyz = _gable_and_ground(rng)
    res = simplify(xyz, cfg=replace(FAST, keep=0.1), rng=np.random.default_rng(0))
    assert res.k == 3
    assert len(res.sse) == 6 and res.sse[0] > res.sse[2] >= res.sse[-1]
    # each cluster is one face orientation: labels agree with the true faces
    truth = np.where(xyz[:, 2] == 0, 0, np.where(xyz[:, 0] < 15, 1, 2))
    inner = (np.abs(xyz[:, 0] - 15) > 0.5) & ~((np.abs(xyz[:, 0] - 15) > 4.5)
                                               & (np.abs(xyz[:, 1] - 15) < 5.5))
    inner &= ~((np.abs(xyz[:, 0] - 15) < 5.5) & (np.abs(np.abs(xyz[:, 1] - 15) - 5) < 0.5))
    for face in range(3):
        labs = res.labels[inner & (truth == face)]
        assert np.mean(labs == np.bincount(labs).argmax()) > 0.97
    # normal_space keeps the requested share and points of every cluster
    assert res.keep.sum() == round(0.1 * len(xyz))
    kept_share = np.bincount(res.labels[res.keep], minlength=3) / np.bincount(res.labels)
    assert kept_share == pytest.approx(0.1, abs=0.01)
    assert np.isfinite(res.r) and res.r > 0.95
    assert res.candidates == () and res.chosen == -1


def test_normal_cluster_chooses_the_best_correlated_large_cluster():
    rng = np.random.default_rng(6)
    xyz = _gable_and_ground(rng)
    res = simplify(xyz, cfg=replace(FAST, method="normal_cluster"), rng=np.random.default_rng(0))
    assert len(res.candidates) == res.k == 3
    best = max((c for c in res.candidates if np.isfinite(c.r)), key=lambda c: c.r)
    assert res.chosen == best.cluster and res.r == best.r
    assert np.array_equal(res.keep, res.labels == res.chosen)
    for c in res.candidates:
        assert c.reduction == pytest.approx(1 - c.points / len(xyz))


def test_first_returns_only():
    rng = np.random.default_rng(7)
    xyz = _plane(rng, n=3000, noise=0.01)
    ret = np.where(rng.random(3000) < 0.2, 2, 1).astype(np.uint8)
    res = simplify(xyz, cfg=replace(FAST, keep=0.5), return_number=ret, rng=rng)
    assert not np.any(res.keep[ret == 2]) and np.all(res.labels[ret == 2] == -1)
    assert np.all(res.labels[ret == 1] >= 0)
    assert res.keep.sum() == round(0.5 * np.sum(ret == 1))
    off = simplify(xyz, cfg=replace(FAST, keep=0.5, first_returns=False), return_number=ret,
                   rng=np.random.default_rng(0))
    assert np.all(off.labels >= 0)
    zeros = simplify(xyz, cfg=FAST, return_number=np.zeros(3000, np.uint8),
                     rng=np.random.default_rng(0))
    assert np.all(zeros.labels >= 0) and "not recorded" in zeros.reason
    quiet = simplify(xyz, cfg=replace(FAST, validate=False), rng=np.random.default_rng(0))
    assert np.isnan(quiet.r) and "validate" not in quiet.timings  # r costs a TIN of all


def test_deterministic_for_a_seed():
    xyz = _gable_and_ground(np.random.default_rng(8))
    a = simplify(xyz, cfg=FAST, rng=np.random.default_rng(42))
    b = simplify(xyz, cfg=FAST, rng=np.random.default_rng(42))
    assert np.array_equal(a.keep, b.keep) and np.array_equal(a.labels, b.labels)
    assert a.r == b.r
    c = simplify(xyz, cfg=FAST)  # rng from cfg.seed
    d = simplify(xyz, cfg=FAST)
    assert np.array_equal(c.keep, d.keep)


@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_tiny_clouds_keep_everything(n):
    xyz = np.random.default_rng(9).uniform(0, 1, (n, 3))
    res = simplify(xyz, cfg=FAST)
    assert res.keep.shape == (n,) and res.keep.all() and res.k == 0
    assert "fewer than" in res.reason and np.isnan(res.r)


@pytest.mark.parametrize("shape", ["coincident", "collinear"])
def test_degenerate_clouds_keep_everything(shape):
    t = np.linspace(0, 10, 50)
    xyz = (np.ones((50, 3)) if shape == "coincident"
           else np.column_stack([t, 2 * t, 0.5 * t]))
    res = simplify(xyz, cfg=FAST)
    assert res.keep.all() and shape in res.reason


def test_vertical_wall_does_not_crash():
    # a wall spans a surface in 3-D but is collinear in XY: no TIN, r is NaN, no Qhull error
    rng = np.random.default_rng(10)
    wall = np.column_stack([rng.uniform(0, 10, 500), np.zeros(500), rng.uniform(0, 5, 500)])
    res = simplify(wall, cfg=replace(FAST, keep=0.2))
    assert res.keep.sum() == 100 and np.isnan(res.r)
    res = simplify(wall, cfg=replace(FAST, method="normal_cluster"))
    assert res.keep.any()


def test_bad_arrays_raise_cloud_format_error():
    with pytest.raises(CloudFormatError):
        simplify(np.array([[0.0, 1.0, np.nan]] * 20), cfg=FAST)
    with pytest.raises(CloudFormatError):
        simplify(np.zeros((20, 2)), cfg=FAST)
    with pytest.raises(CloudFormatError):
        simplify(np.zeros((20, 3)), cfg=FAST, return_number=np.ones(3))


def test_normal_space_sample_rare_orientation_survives():
    rng = np.random.default_rng(11)
    xyz = rng.uniform(0, 10, (1000, 3))
    labels = np.zeros(1000, dtype=np.int32)
    labels[:3] = 1  # a rare orientation: 3 points
    keep = normal_space_sample(xyz, labels, 50, rng)
    assert keep.sum() == 50 and keep[:3].any()


def test_a_stray_point_far_away_is_dropped_not_the_simplification():
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 50, (5000, 2)), rng.normal(0, 0.05, 5000)])
    res = simplify(np.vstack([xyz, [1e30, 0.0, 0.0]]), cfg=SimplifyConfig())
    assert not res.keep[-1] and "1 stray points" in res.reason
    assert 0.15 < res.keep[:-1].mean() < 0.21  # simplified as without it
