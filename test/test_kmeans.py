"""K-means, elbow, TIN outlier checks and the automatic ground cluster (core.kmeans)."""
from __future__ import annotations

import logging
import warnings

import numpy as np
import pytest

from conftest import data_file
from lidar_obstacles.config import KmeansConfig
from lidar_obstacles.core.kmeans import (elbow_kmeans, geometric_features, intensity_problem,
                                         kmeans, kmeans_ground, knee_index,
                                         lower_envelope_filter, standardise,
                                         tin_outlier_filter)
from lidar_obstacles.errors import CloudFormatError


def test_standardise_known_answer():
    x = np.array([[1.0, 5.0], [2.0, 5.0], [3.0, 5.0], [6.0, 5.0]])
    z, mean, std = standardise(x)
    assert mean == pytest.approx([3.0, 5.0])
    assert std[0] == pytest.approx(np.sqrt(14.0 / 3.0))  # N - 1 in the denominator
    assert z[:, 0] == pytest.approx((x[:, 0] - 3.0) / np.sqrt(14.0 / 3.0))
    assert std[1] == 0 and np.all(z[:, 1] == 0)  # constant column: zeros, no division by 0
    assert z[:, 0].std(ddof=1) == pytest.approx(1.0)


def _blobs_1d(rng, n=2000):
    means = (100.0, 300.0, 700.0, 1500.0)
    return np.concatenate([rng.normal(m, 10.0, n) for m in means]).round().astype(np.uint16)


def test_kmeans_1d_exact_on_separated_groups():
    x = np.array([0.0, 0.1, 0.2, 10.0, 10.1, 10.2, 20.0, 20.2])
    res = kmeans(x, 3, restarts=5, rng=1)
    assert np.sort(res.centres[:, 0]) == pytest.approx([0.1, 10.1, 20.1])
    expected_sse = 4 * 0.01 + 2 * 0.01
    assert res.sse == pytest.approx(expected_sse)
    assert len(np.unique(res.labels[:3])) == 1 and res.labels[0] != res.labels[3]


def test_kmeans_1d_matches_sklearn_sse():
    from sklearn.cluster import KMeans

    x = standardise(_blobs_1d(np.random.default_rng(0)).astype(float))[0]
    for k in (2, 5, 7):
        ours = kmeans(x, k, restarts=10, rng=0).sse
        ref = KMeans(k, n_init=10, random_state=0).fit(x[:, None]).inertia_
        assert ours <= ref * (1 + 1e-6)


def test_kmeans_deterministic_and_validates():
    x = np.random.default_rng(3).normal(size=(500, 2))
    a, b = kmeans(x, 4, rng=7), kmeans(x, 4, rng=7)
    assert np.array_equal(a.labels, b.labels) and a.sse == b.sse
    with pytest.raises(CloudFormatError):
        kmeans(x, 501)
    with pytest.raises(CloudFormatError):
        kmeans(np.array([1.0, np.nan]), 1)


def test_elbow_finds_k_on_blobs():
    rng = np.random.default_rng(2)
    one_d = elbow_kmeans(standardise(_blobs_1d(rng).astype(float))[0], max_k=10, rng=0)
    assert one_d.k == 4 and len(one_d.sse) == 10
    assert np.all(np.diff(one_d.sse) <= 1e-9 * one_d.sse[0])
    centres = [(0, 0, 0), (6, 0, 0), (0, 6, 0), (6, 6, 6), (3, 3, 12)]
    x = np.concatenate([rng.normal(c, 0.4, (600, 3)) for c in centres])
    multi = elbow_kmeans(standardise(x)[0], max_k=10, restarts=3, sample_size=1500, rng=0)
    assert multi.k == 5
    assert len(multi.result.labels) == len(x)  # every sample assigned, not just the subset
    assert len(np.unique(multi.result.labels)) == 5


@pytest.mark.parametrize("x", [np.repeat([0.0, 10.0, 11.0], 30),  # one feature: SSE 0 at 3
                               np.repeat(np.eye(4), 30, axis=0),  # 4 rows: SSE 0 at k = 4
                               np.repeat(np.eye(3) * [1.0, 10.0, 11.0], 30, axis=0)])
def test_elbow_of_a_few_distinct_samples_is_their_number(x):
    # the sweep stopped at the first SSE of 0 and the knee of that curve was k = 1; with
    # several features it swept on past the distinct rows, a ConvergenceWarning each k
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = elbow_kmeans(x, max_k=10)
    distinct = len(np.unique(x, axis=0))
    assert res.k == distinct and len(res.sse) == distinct
    assert len(np.unique(res.result.labels)) == distinct


def test_knee_of_flat_and_sharp_curves():
    assert knee_index(np.array([5.0, 5.0, 5.0])) == 0
    assert knee_index(np.array([100.0, 50.0, 2.0, 1.5, 1.0, 0.8])) == 2


def test_tin_outlier_filter_drops_spike_and_pit_keeps_plane():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 50, (2000, 2))
    z = 0.1 * xy[:, 0] - 0.05 * xy[:, 1]
    z[10] += 3.0
    z[20] -= 2.0
    keep = tin_outlier_filter(np.column_stack([xy, z]), threshold=0.5, max_rounds=5)
    assert not keep[10] and not keep[20]
    assert keep.sum() == 1998
    # degenerate input: nothing dropped, no Qhull error
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.arange(10.0) % 3])
    assert tin_outlier_filter(line, threshold=0.1, max_rounds=3).all()


def test_lower_envelope_drops_low_patches_keeps_sloping_ground():
    rng = np.random.default_rng(9)
    xy = rng.uniform(0, 60, (6000, 2))
    z = 0.3 * xy[:, 0]  # a 30 % slope: no loss inside; the rim beyond the minima's hull
    # is judged against the nearest minima and loses points where slope x distance > 0.5
    hedge = (np.abs(xy[:, 0] - 30) < 4) & (np.abs(xy[:, 1] - 30) < 4)
    z[hedge] += 1.5  # an 8 x 8 m patch 1.5 m up: smooth, level, invisible to neighbours
    keep = lower_envelope_filter(np.column_stack([xy, z]), cell=10.0, threshold=0.5)
    assert not keep[hedge].any()
    inner = (xy[:, 0] > 10) & (xy[:, 0] < 50) & (xy[:, 1] > 10) & (xy[:, 1] < 50)
    assert keep[~hedge & inner].all()
    assert keep[~hedge].mean() > 0.8


def _scene(rng, intensity_for_ground=(200, 400)):
    """A 60 x 60 m sloping ground with two intensity classes and a 20 x 20 m roof at +6 m."""
    ground = rng.uniform(0, 60, (12000, 2))
    gz = 0.05 * ground[:, 0] + rng.normal(0, 0.03, len(ground))
    gi = np.where(ground[:, 0] < 30, *intensity_for_ground) + rng.normal(0, 15, len(ground))
    roof = rng.uniform(20, 40, (3000, 2))
    rz = 0.05 * roof[:, 0] + 6.0 + rng.normal(0, 0.03, len(roof))
    ri = 900 + rng.normal(0, 15, len(roof))
    xyz = np.vstack([np.column_stack([ground, gz]), np.column_stack([roof, rz])])
    inten = np.concatenate([gi, ri]).clip(0).astype(np.uint16)
    truth = np.r_[np.ones(len(ground), bool), np.zeros(len(roof), bool)]
    return xyz, inten, truth


@pytest.mark.parametrize("features", ["intensity", "two_stage", "geometric"])
def test_kmeans_ground_picks_ground_automatically(features):
    rng = np.random.default_rng(5)
    xyz, inten, truth = _scene(rng)
    found = kmeans_ground(xyz, cfg=KmeansConfig(features=features, restarts=3),
                          intensity=inten)
    assert found.reason == "" and found.features == features  # (no silent fallback)
    precision = (found.ground & truth).sum() / found.ground.sum()
    recall = (found.ground & truth).sum() / truth.sum()
    assert precision > 0.98 and recall > 0.8, (features, precision, recall)


def test_missing_or_flag_intensity_falls_back_to_geometry(caplog, monkeypatch):
    import lidar_obstacles.core.kmeans as km

    monkeypatch.setattr(km, "_warned", set())
    rng = np.random.default_rng(6)
    xyz, _, truth = _scene(rng)
    assert "no intensity" in intensity_problem(None)
    flag = (~truth).astype(np.uint16)  # ISPRS-style: intensity repeats the label
    assert "2 distinct" in intensity_problem(flag)
    with caplog.at_level(logging.WARNING):
        found = kmeans_ground(xyz, cfg=KmeansConfig(restarts=3), intensity=flag)
        again = kmeans_ground(xyz, cfg=KmeansConfig(restarts=3), intensity=flag)
    assert found.features == "geometric" and "distinct" in found.reason
    assert again.reason == found.reason  # the flag stays in every result...
    assert sum("geometric" in r.getMessage() for r in caplog.records) == 1  # ...logged once
    assert (found.ground & truth).sum() / found.ground.sum() > 0.98


def test_kmeans_ground_tiny_input():
    found = kmeans_ground(np.zeros((2, 3)), cfg=KmeansConfig())
    assert found.ground.all() and "only 2 points" in found.reason


def test_geometric_features_shape_and_meaning():
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 20, (3000, 2))
    xyz = np.column_stack([xy, np.zeros(len(xy))])
    f = geometric_features(xyz, window=10.0)
    assert f.shape == (3000, 3)
    assert np.allclose(f[:, 0], 0) and np.allclose(f[:, 1], 0, atol=1e-9)
    assert np.allclose(f[:, 2], 1.0)  # level ground: normal straight up


def test_real_isprs_geometric_ground():
    from lidar_obstacles.io.las import read_las

    cloud = read_las(data_file("isprs/samp52-utm.laz"))
    truth = cloud.points["classification"] == 2
    # ISPRS intensity repeats the label: the caller does not pass it
    found = kmeans_ground(cloud.xyz, cfg=KmeansConfig(features="geometric", restarts=3))
    precision = (found.ground & truth).sum() / found.ground.sum()
    assert precision > 0.95  # measured 0.988
    assert found.ground.sum() > 0.3 * truth.sum()


def test_elbow_sweep_runs_every_restart_for_every_k(monkeypatch):
    """k = 1..10 with 10 restarts is 100 Lloyd runs, each from its own K-means++ seeds."""
    from lidar_obstacles.core import kmeans as km

    seeds, runs = [], [0]
    seed_fn, lloyd_fn = km._kmeanspp_1d, km._lloyd_1d

    def seeding(*a, **kw):
        seeds.append(tuple(out := seed_fn(*a, **kw)))
        return out

    def lloyd(*a, **kw):
        runs[0] += 1
        return lloyd_fn(*a, **kw)

    monkeypatch.setattr(km, "_kmeanspp_1d", seeding)
    monkeypatch.setattr(km, "_lloyd_1d", lloyd)
    x = np.random.default_rng(0).normal(size=5000)  # continuous: no early stop at SSE 0
    res = km.elbow_kmeans(x, max_k=10, restarts=10, rng=0)
    assert len(res.sse) == 10 and runs[0] == 100 and len(seeds) == 100
    assert len(set(seeds[30:40])) > 1  # the restarts of one k start from different seeds


def test_several_features_are_fitted_on_one_thread_and_the_pools_come_back(monkeypatch):
    """scikit-learn's OpenMP threads spin-wait on a busy machine (35 s for a 0.6 s sweep):
    every fit runs with its thread pools on one thread, and leaves them as they were."""
    from sklearn.cluster import KMeans
    from threadpoolctl import threadpool_info

    def openmp_threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "openmp"}

    seen: list[set[int]] = []
    fit = KMeans.fit

    def recording_fit(self, *args, **kwargs):
        seen.append(openmp_threads())
        return fit(self, *args, **kwargs)

    monkeypatch.setattr(KMeans, "fit", recording_fit)
    before = openmp_threads()
    x = np.random.default_rng(3).normal(size=(500, 3))
    for _ in range(2):  # (the second fit reuses the pools found by the first)
        kmeans(x, 3, restarts=2)
    assert seen == [{1}, {1}]
    assert openmp_threads() == before
