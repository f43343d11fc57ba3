"""Interpolators with known answers (lidar_obstacles.core.interpolate)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_obstacles.config import KrigingConfig, RbfConfig, RbfnnConfig
from lidar_obstacles.config import DemBuilderConfig
from lidar_obstacles.core.interpolate import (METHODS, Variogram, choose_nugget, degeneracy,
                                              fit_variogram, interpolate, kriging_variogram,
                                              merge_coincident, tin, train_rbfnn)
from lidar_obstacles.errors import CloudFormatError


def _samples(n=1500, seed=0, size=50.0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, size, (n, 2))


def _queries(lo=10.0, hi=40.0, step=1.3):
    g = np.arange(lo, hi, step)
    return np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)


def plane(p):
    return 3.0 + 0.2 * p[:, 0] - 0.1 * p[:, 1]


def paraboloid(p):
    return 0.01 * ((p[:, 0] - 25) ** 2 + (p[:, 1] - 25) ** 2)


@pytest.mark.parametrize("method", ["tin", "rbf"])
def test_plane_is_exact_for_linear_methods(method):
    xy, q = _samples(), _queries()
    out = interpolate(method, xy, plane(xy), q)
    assert np.allclose(out, plane(q), atol=1e-6)


@pytest.mark.parametrize("method,tol", [("idw", 0.1), ("kriging", 0.01), ("rbfnn", 0.2)])
def test_plane_is_close_for_the_others(method, tol):
    xy, q = _samples(), _queries()
    out = interpolate(method, xy, plane(xy), q, rbfnn_cfg=RbfnnConfig(goal=1e-3))
    assert np.sqrt(np.mean((out - plane(q)) ** 2)) < tol


@pytest.mark.parametrize("method,tol", [("tin", 0.02), ("idw", 0.1), ("kriging", 0.02),
                                        ("rbf", 0.002), ("rbfnn", 0.1)])
def test_paraboloid_small_error(method, tol):
    xy, q = _samples(), _queries()
    out = interpolate(method, xy, paraboloid(xy), q, rbfnn_cfg=RbfnnConfig(goal=1e-3,
                                                                           spread=0.5))
    rmse = np.sqrt(np.mean((out - paraboloid(q)) ** 2))
    assert rmse < tol, rmse


@pytest.mark.parametrize("method", ["tin", "idw"])
def test_step_has_no_overshoot(method):
    xy = _samples(2000, seed=1)
    z = np.where(xy[:, 0] < 25, 0.0, 2.0)
    out = interpolate(method, xy, z, _queries())
    assert out.min() >= -1e-9 and out.max() <= 2.0 + 1e-9
    far = _queries()
    assert np.allclose(out[far[:, 0] < 20], 0.0) and np.allclose(out[far[:, 0] > 30], 2.0)


def test_hole_filled_inside_and_nan_outside_hull_for_tin():
    xy = _samples(3000, seed=2)
    hole = np.hypot(xy[:, 0] - 25, xy[:, 1] - 25) < 8
    xy = xy[~hole]
    q = np.array([[25.0, 25.0], [22.0, 27.0], [80.0, 80.0], [-5.0, 10.0]])
    for method in METHODS:
        out = interpolate(method, xy, plane(xy), q, rbfnn_cfg=RbfnnConfig(goal=1e-4))
        if method == "tin":
            assert np.allclose(out[:2], plane(q[:2]), atol=1e-9)
            assert np.isnan(out[2:]).all()
        else:
            assert np.isfinite(out).all()
            # IDW flattens towards the rim's mean and ordinary kriging reverts to the mean
            # beyond its variogram range; RBFs follow the plane
            tol = 0.1 if method in ("rbf", "rbfnn") else 1.0
            assert np.allclose(out[:2], plane(q[:2]), atol=tol), (method, out[:2])


def test_exact_at_samples():
    xy = _samples(400, seed=3)
    z = paraboloid(xy) + np.random.default_rng(3).normal(0, 0.1, len(xy))
    for method in ("tin", "idw", "kriging", "rbf"):
        assert np.allclose(interpolate(method, xy, z, xy[:50]), z[:50], atol=1e-6), method


@pytest.mark.parametrize("method", METHODS)
def test_degenerate_inputs_never_raise(method):
    q = _queries(0, 10, 2.5)
    empty = interpolate(method, np.zeros((0, 2)), np.zeros(0), q)
    assert empty.shape == (len(q),) and np.isnan(empty).all()
    one = interpolate(method, np.array([[1.0, 1.0]]), np.array([5.0]), q)
    two = interpolate(method, np.array([[1.0, 1.0], [3.0, 1.0]]), np.array([5.0, 5.0]), q)
    line_xy = np.column_stack([np.linspace(0, 10, 20), np.linspace(0, 5, 20)])
    line = interpolate(method, line_xy, line_xy[:, 0], q)
    same = interpolate(method, np.ones((5, 2)), np.arange(5.0), q)  # 5 coincident points
    if method == "tin":
        for out in (one, two, line, same):
            assert np.isnan(out).all()
    else:
        assert np.allclose(one, 5.0) and np.allclose(two, 5.0) and np.allclose(same, 2.0)
        assert np.isfinite(line).all()


def test_degeneracy_reasons_and_merging():
    assert "only 2" in degeneracy(np.zeros((2, 2)))
    assert "collinear" in degeneracy(np.column_stack([np.arange(5.0), 2 * np.arange(5.0)]))
    assert degeneracy(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])) == ""
    xy, z = merge_coincident(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0], [np.nan, 0.0]]),
                             np.array([1.0, 3.0, 5.0, 7.0]))
    assert len(xy) == 2 and sorted(z) == [2.0, 5.0]


def test_flat_plane_gives_flat_surface():
    xy, q = _samples(300), _queries()
    assert len(q) == 24 * 24
    for method in METHODS:
        out = interpolate(method, xy, np.full(len(xy), 7.0), q)
        # the queries (10..40 m) lie well inside the samples' hull (0..50 m): all defined
        assert out.shape == (len(q),) and np.isfinite(out).all(), method
        assert np.allclose(out, 7.0), method


def test_bad_input_raises_typed_errors():
    with pytest.raises(CloudFormatError):
        interpolate("spline", np.zeros((3, 2)), np.zeros(3), np.zeros((1, 2)))
    with pytest.raises(CloudFormatError):
        interpolate("tin", np.zeros((3, 3)), np.zeros(3), np.zeros((1, 2)))
    with pytest.raises(CloudFormatError):
        interpolate("tin", np.zeros((3, 2)), np.zeros(4), np.zeros((1, 2)))


def test_variogram_fit_is_sensible():
    xy = _samples(2000, seed=4)
    z = paraboloid(xy)
    for model in ("spherical", "exponential", "gaussian", "linear"):
        vg = fit_variogram(xy, z, model=model, neighbours=16)
        h = np.array([0.0, 1.0, 5.0, 20.0])
        g = vg(h)
        assert g[0] == 0 and np.all(np.diff(g) >= -1e-12), model
        assert vg.nugget < 0.1 * max(g[-1], 1e-9), model


@pytest.mark.parametrize("variogram", ["spherical", "exponential", "gaussian", "linear"])
def test_kriging_variograms_all_solve(variogram):
    xy, q = _samples(), _queries()
    out = interpolate("kriging", xy, paraboloid(xy), q,
                      kriging_cfg=KrigingConfig(variogram=variogram, neighbours=12))
    assert np.sqrt(np.mean((out - paraboloid(q)) ** 2)) < 0.02


@pytest.mark.parametrize("kernel", ["thin_plate_spline", "multiquadric", "gaussian", "linear",
                                    "cubic"])
def test_rbf_kernels_all_solve(kernel):
    xy, q = _samples(), _queries()
    out = interpolate("rbf", xy, paraboloid(xy), q, rbf_cfg=RbfConfig(kernel=kernel,
                                                                      neighbours=24))
    assert np.sqrt(np.mean((out - paraboloid(q)) ** 2)) < 0.05


def test_rbfnn_reaches_its_goal_on_a_smooth_surface():
    xy = _samples(3000, seed=5)
    z = 2.0 * np.sin(xy[:, 0] / 10.0) + np.cos(xy[:, 1] / 8.0)
    net = train_rbfnn(xy, z, goal=1e-3, spread=0.5, max_neurons=300)
    assert net.mse <= 1e-3 and net.neurons < 300
    pred = net.predict(xy)
    assert np.mean((pred - z) ** 2) == pytest.approx(net.mse, rel=1e-6, abs=1e-9)
    capped = train_rbfnn(xy, z, goal=1e-12, spread=0.5, max_neurons=5)
    assert capped.neurons == 5 and capped.mse > 1e-3


def test_rbfnn_uses_intensity_when_given():
    xy = _samples(1000, seed=6)
    inten = np.where(xy[:, 0] > 25, 100.0, 10.0)
    z = 0.01 * inten + 0.0 * xy[:, 1]
    q = np.array([[10.0, 10.0], [40.0, 10.0]])
    cfg = RbfnnConfig(goal=1e-4)
    out = interpolate("rbfnn", xy, z, q, rbfnn_cfg=cfg, intensity=inten,
                      query_intensity=np.array([10.0, 100.0]))
    assert out == pytest.approx([0.1, 1.0], abs=0.05)


def test_rbfnn_generalises_and_adds_units_where_error_is_largest():
    xy = _samples(3000, seed=7)
    z = 2.0 * np.sin(xy[:, 0] / 10.0) + np.cos(xy[:, 1] / 8.0)
    q = _samples(500, seed=8)
    truth = 2.0 * np.sin(q[:, 0] / 10.0) + np.cos(q[:, 1] / 8.0)
    net = train_rbfnn(xy, z, goal=1e-3, spread=0.5, max_neurons=300)
    assert np.sqrt(np.mean((net.predict(q) - truth) ** 2)) < 0.05  # held out: no overfit
    # newrb's rule: the first unit sits on the sample farthest from the mean (the bias)
    first = train_rbfnn(xy, z, goal=1e-12, spread=0.5, max_neurons=1)
    worst = np.argmax(np.abs(z - z.mean()))
    assert np.allclose(first.centres[0] * first.std + first.mean, xy[worst])


def test_tin_scattered_queries_fast_and_same_as_ordered(monkeypatch):
    # Qhull's walk fell back to a search over all triangles for random-order queries and
    # for queries outside the hull (0.5-5 s here): tin() hands Qhull only the queries
    # inside the hull, in row order, each a step from the last.
    from scipy.spatial import Delaunay

    xy = np.random.default_rng(3).uniform(0, 300, (4000, 2))
    z = plane(xy)
    q = np.random.default_rng(4).uniform(-10, 310, (16000, 2))
    asked: list[np.ndarray] = []
    find = Delaunay.find_simplex

    def recorded(self, points, *args, **kwargs):
        asked.append(np.array(points))
        return find(self, points, *args, **kwargs)

    monkeypatch.setattr(Delaunay, "find_simplex", recorded)
    out = tin(xy, z, q)
    monkeypatch.undo()
    walk = np.concatenate(asked)
    assert 0.85 * len(q) < len(walk) < len(q)  # the hull screens the outside ones out
    steps = np.hypot(*np.diff(walk, axis=0).T)
    assert np.median(steps) < 10.0  # m (rows one sample spacing, 4.7 m, high); random: ~150 m
    inside = np.isfinite(out)
    assert inside.mean() > 0.85 and np.allclose(out[inside], plane(q[inside]), atol=1e-6)
    order = np.argsort(q[:, 0])
    again = tin(xy, z, q[order])
    both = np.isfinite(again) & inside[order]
    assert np.mean(np.isfinite(again) != inside[order]) < 1e-3  # only points on the hull
    assert np.allclose(again[both], out[order][both], atol=1e-9)


def test_nugget_cross_validation_exact_without_noise_smooth_with_noise():
    xy = _samples(3000, seed=9)
    smooth = 0.5 * np.sin(xy[:, 0] / 7.0) + 0.3 * np.cos(xy[:, 1] / 5.0)
    vg = fit_variogram(xy, smooth, model="spherical", neighbours=16)
    assert choose_nugget(xy, smooth, vg, neighbours=16).nugget == 0.0
    noisy = smooth + np.random.default_rng(10).normal(0, 0.05, len(xy))
    chosen = kriging_variogram(xy, noisy, cfg=KrigingConfig())
    assert chosen.nugget > 0.0
    # the chosen nugget predicts held-out truth better than the exact interpolator
    q = _queries(5, 45, 0.7)
    truth = 0.5 * np.sin(q[:, 0] / 7.0) + 0.3 * np.cos(q[:, 1] / 5.0)
    exact = Variogram(chosen.model, 0.0, chosen.partial_sill, chosen.range_)

    def err(v):
        return np.sqrt(np.mean((interpolate("kriging", xy, noisy, q, variogram=v) - truth) ** 2))

    assert err(chosen) < 0.9 * err(exact)
    # too few samples to cross-validate: the fitted variogram is kept
    assert choose_nugget(xy[:100], noisy[:100], vg, neighbours=16) == vg


def test_default_interpolator_not_worse_than_tin_and_idw_on_noisy_terrain():
    """The rule bench_dem.py checks on real data, on a synthetic survey: rolling terrain
    with a ditch, 3 cm noise, thinned to 20 % and 80 %, scored on every held-out point."""
    rng = np.random.default_rng(11)
    xy = rng.uniform(0, 60, (12000, 2))

    def terrain(p):
        return (0.8 * np.sin(p[:, 0] / 9.0) * np.cos(p[:, 1] / 11.0)
                - 0.5 * np.exp(-((p[:, 0] - 30) / 2.0) ** 2))

    z = terrain(xy) + rng.normal(0, 0.03, len(xy))
    default = DemBuilderConfig().dem.interpolation
    for keep in (0.2, 0.8):
        n = int(keep * len(xy))
        train, test = slice(0, n), slice(n, None)

        def rmse(m):
            p = interpolate(m, xy[train], z[train], xy[test])
            ok = np.isfinite(p)
            return np.sqrt(np.mean((p[ok] - terrain(xy[test][ok])) ** 2))

        assert rmse(default) <= min(rmse("tin"), rmse("idw"))


def test_far_queries_share_neighbourhoods_near_ones_do_not(monkeypatch):
    """A grid's margin beyond the samples (a rolling DEM's fill_distance) is solved in
    blocks that widen with the distance from the samples; near them nothing changes."""
    import lidar_obstacles.core.interpolate as interp

    xy = _samples(2000, seed=5)
    z = paraboloid(xy)
    near = _queries(5.0, 45.0, 1.0)
    far = _queries(-25.0, 75.0, 1.0)
    far = far[(np.abs(far - 25.0) > 27.0).any(axis=1)]  # 2-25 m beyond the samples
    blocks = interp._blocks(xy, far, 16)
    assert len(blocks.centre) < len(far) / 3
    cfg = KrigingConfig()
    both = interpolate("kriging", xy, z, np.concatenate([near, far]), kriging_cfg=cfg)
    alone = interpolate("kriging", xy, z, near, kriging_cfg=cfg)
    np.testing.assert_allclose(both[:len(near)], alone, rtol=0, atol=1e-9)
    monkeypatch.setattr(interp, "_MAX_BLOCK_LEVEL", 0)  # one block per sample spacing
    each = interpolate("kriging", xy, z, far, kriging_cfg=cfg)
    # Out there both extrapolate the paraboloid poorly, and as poorly as each other.
    truth = paraboloid(far)
    rmse_blocks = np.sqrt(np.mean((both[len(near):] - truth) ** 2))
    rmse_each = np.sqrt(np.mean((each - truth) ** 2))
    assert rmse_blocks < 1.01 * rmse_each
    assert np.mean(np.abs(both[len(near):] - each)) < 0.05 * rmse_each


def test_rbfnn_answers_within_the_samples_heights():
    """A few units fitted to a step overshoot it between and beyond the samples; the DEM
    keeps to the samples' range (a bias and bumps carry no trend beyond them)."""
    xy = _samples(400, seed=9)
    z = np.where(xy[:, 0] > 25, 10.0, 0.0)
    q = np.column_stack([np.linspace(-50, 100, 300), np.full(300, 25.0)])
    cfg = RbfnnConfig(goal=1e-6, spread=0.3, max_neurons=40)
    net = train_rbfnn(xy, z, goal=cfg.goal, spread=cfg.spread, max_neurons=cfg.max_neurons)
    raw = net.predict(q)
    assert raw.min() < -0.5 or raw.max() > 10.5  # the network alone leaves the range
    out = interpolate("rbfnn", xy, z, q, rbfnn_cfg=cfg)
    assert out.min() >= 0.0 and out.max() <= 10.0
    inside = (raw >= 0.0) & (raw <= 10.0)
    assert np.array_equal(out[inside], raw[inside])


@pytest.mark.parametrize("power, expected", [(1.0, 1.0), (2.0, 0.6), (3.0, 1 / 3)])
def test_idw_weights_are_one_over_distance_to_the_power(power, expected):
    # samples 1 m (z = 0) and 2 m (z = 3) from the query: weights 1 and 1 / 2^p, so
    # z = 3 / 2^p / (1 + 1 / 2^p): p = 1 -> 1.0, p = 2 -> 0.6, p = 3 -> 1/3
    z = interpolate("idw", np.array([[1.0, 0.0], [0.0, 2.0]]), np.array([0.0, 3.0]),
                    np.array([[0.0, 0.0]]), idw_neighbours=2, idw_power=power)
    assert z[0] == pytest.approx(expected)
