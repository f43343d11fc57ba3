"""Tests of the synthetic UAV LiDAR flight (lidar_obstacles.core.simulate)."""
from __future__ import annotations

import dataclasses
import itertools
import tracemalloc

import numpy as np
import pytest

from lidar_obstacles.core.simulate import (
    POINT_DTYPE,
    SCENES,
    SimFrame,
    SimSettings,
    scene_ground_height,
    scene_info,
    simulate_flight,
)
from lidar_obstacles.errors import CloudFormatError, ConfigError

VEGETATION = (3, 4, 5)


def _flight(**kw) -> list[SimFrame]:
    return list(simulate_flight(SimSettings(**kw)))


def _points(frames: list[SimFrame]) -> np.ndarray:
    return np.concatenate([f.points for f in frames])


def _rotation(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def mixed() -> list[SimFrame]:
    """The default demo flight (20 s of the mixed scene), at a lighter point count."""
    return _flight(scene="mixed", duration=20.0, points_per_frame=15_000)


# --------------------------------------------------------------------------- settings


@pytest.mark.parametrize("kw", [
    {"scene": "moon"}, {"frame": "odom"}, {"duration": 0.0}, {"duration": -1.0},
    {"rate": 0.0}, {"altitude": 1.0}, {"speed": -1.0}, {"points_per_frame": 0},
    {"points_per_frame": 1.5}, {"seed": -1}, {"seed": 1.5}, {"fov_across": 170.0},
    {"wire_radius": 0.0}, {"max_returns": 0}, {"range_noise": float("nan")},
    {"duration": 1e6, "points_per_frame": 1_000_000},
])
def test_bad_settings_raise_config_error(kw):
    with pytest.raises(ConfigError):
        SimSettings(**kw)


def test_bad_arguments():
    with pytest.raises(ConfigError):
        simulate_flight("mixed")  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        scene_ground_height("moon", np.zeros((1, 2)))
    with pytest.raises(CloudFormatError):
        scene_ground_height("mixed", np.zeros((4, 3)))


# --------------------------------------------------------------------------- determinism


def test_same_seed_same_bytes_other_seed_differs():
    kw = dict(duration=0.3, points_per_frame=5000)
    a = _flight(seed=3, **kw)
    b = _flight(seed=3, **kw)
    c = _flight(seed=4, **kw)
    assert len(a) == len(b) == 3
    for fa, fb in zip(a, b):
        assert fa.points.tobytes() == fb.points.tobytes()
        assert fa.position.tobytes() == fb.position.tobytes()
        assert fa.orientation.tobytes() == fb.orientation.tobytes()
    assert a[0].points.tobytes() != c[0].points.tobytes()
    # Different seeds also give different scenes.
    xy = np.array([[100.0, 200.0], [-300.0, 50.0]])
    assert not np.allclose(scene_ground_height(SimSettings(seed=3), xy),
                           scene_ground_height(SimSettings(seed=4), xy))


# --------------------------------------------------------------------------- frames


def test_frame_layout_stamps_and_ids(mixed):
    assert len(mixed) == 200
    stamps = np.array([f.stamp for f in mixed])
    np.testing.assert_allclose(stamps, np.arange(200) / 10.0)
    for f in mixed[:3]:
        assert f.points.dtype == POINT_DTYPE
        assert f.position.shape == (3,) and f.position.dtype == np.float64
        assert f.orientation.shape == (4,) and f.velocity.shape == (3,)
        assert abs(np.linalg.norm(f.orientation) - 1.0) < 1e-12
    ids = _points(mixed)["point_id"].astype(np.int64)
    assert ids[0] == 0
    assert np.all(np.diff(ids) == 1)      # unique and increasing over the whole flight


@pytest.mark.parametrize("scene", SCENES)
def test_points_per_frame_near_the_setting(scene):
    frames = _flight(scene=scene, duration=1.5, points_per_frame=20_000)
    counts = np.array([len(f.points) for f in frames[5:]])
    assert np.all(np.abs(counts - 20_000) < 0.15 * 20_000), counts
    assert abs(counts.mean() - 20_000) < 0.05 * 20_000


def test_mixed_scene_has_every_class(mixed):
    cls = set(np.unique(_points(mixed)["classification"]).tolist())
    assert cls == {1, 2, 3, 4, 5, 6, 7, 14, 15}


@pytest.mark.parametrize("scene, expected, absent", [
    ("corridor", {2, 5, 7, 14, 15}, {6}),
    ("urban", {1, 2, 5, 6, 7}, {14, 15}),
    ("forest", {2, 3, 4, 5, 7}, {14, 15}),
])
def test_other_scenes_classes(scene, expected, absent):
    cls = set(np.unique(_points(_flight(scene=scene, duration=3.0,
                                        points_per_frame=10_000))["classification"]).tolist())
    assert expected <= cls, (scene, cls)
    assert not (absent & cls), (scene, cls)


# --------------------------------------------------------------------------- geometry


def test_ground_points_lie_on_the_true_terrain(mixed):
    p = _points(mixed)
    g = p[p["classification"] == 2]
    h = scene_ground_height("mixed", np.column_stack([g["x"], g["y"]]).astype(np.float64))
    dz = g["z"] - h
    assert abs(dz.mean()) < 0.005
    assert dz.std() < 0.03                 # 2.5 cm range noise, beams near nadir
    assert np.abs(dz).max() < 0.2


def test_vegetation_classes_follow_height_above_ground(mixed):
    p = _points(mixed)
    hag = p["z"] - scene_ground_height("mixed", np.column_stack([p["x"], p["y"]]))
    cls = p["classification"]
    assert np.all(hag[cls == 3] < 0.5)
    assert np.all((hag[cls == 4] >= 0.5) & (hag[cls == 4] < 2.0))
    assert np.all(hag[cls == 5] >= 2.0)
    noise = cls == 7
    assert np.all(np.abs(hag[noise]) > 2.0)   # outliers are far from the surface


def test_wires_hang_between_towers_10_to_40_m_above_ground(mixed):
    p = _points(mixed)
    w = p[p["classification"] == 14]
    assert len(w) > 1000
    xy = np.column_stack([w["x"], w["y"]]).astype(np.float64)
    hag = w["z"] - scene_ground_height("mixed", xy)
    assert hag.min() >= 10.0 and hag.max() <= 41.0
    info = scene_info("mixed")
    # Every wire point is inside the corridor of a span: between its two towers (the
    # arms of angle towers reach a little past them), no farther from the span axis
    # than the longest cross-arm.
    inside = np.zeros(len(w), bool)
    for i, j in info.spans:
        a, b = info.towers[i, :2], info.towers[j, :2]
        ab = b - a
        s = (xy - a) @ ab / (ab @ ab)
        off = np.abs((xy - a) @ np.array([-ab[1], ab[0]]) / np.linalg.norm(ab))
        inside |= (s > -0.03) & (s < 1.03) & (off < 8.0)
    assert inside.all()
    # The classifier needs points all along the wires: over the 40 m of wire crossed by
    # the flight line, hits every metre or better along the earth wire and conductors.
    near = np.abs(xy[:, 1]) < 10.0
    bins = np.unique(np.floor(xy[near, 1]).astype(int))
    assert len(bins) == 20


def test_towers_stand_on_the_ground(mixed):
    p = _points(mixed)
    t = p[p["classification"] == 15]
    assert len(t) > 500
    info = scene_info("mixed")
    d = np.hypot(t["x"][:, None] - info.towers[None, :, 0],
                 t["y"][:, None] - info.towers[None, :, 1]).min(axis=1)
    assert d.max() < 9.0                  # within the cross-arms of some tower
    assert np.all(info.tower_heights > 25.0)


def test_sensor_frame_transforms_back_with_the_pose():
    kw = dict(scene="corridor", duration=0.5, points_per_frame=8000)
    in_map = _flight(frame="map", **kw)
    in_sensor = _flight(frame="sensor", **kw)
    assert len(in_map) == len(in_sensor) == 5
    for fm, fs in zip(in_map, in_sensor):
        assert fm.position.tobytes() == fs.position.tobytes()
        ps = np.column_stack([fs.points["x"], fs.points["y"], fs.points["z"]]).astype(float)
        pm = np.column_stack([fm.points["x"], fm.points["y"], fm.points["z"]]).astype(float)
        back = ps @ _rotation(fs.orientation).T + fs.position
        np.testing.assert_allclose(back, pm, atol=2e-3)
        for name in ("intensity", "classification", "point_id", "return_number"):
            assert np.array_equal(fm.points[name], fs.points[name])
        # Sensor frame: x forward, y left, z up: the ground is below, the swath is wide
        # across track (y) and short along it (x).
        ground = fs.points[fs.points["classification"] == 2]
        assert np.median(ground["z"]) < -30.0
        assert np.ptp(ground["y"]) > 2.5 * np.ptp(ground["x"])


def test_pose_follows_the_terrain_at_the_set_height_and_speed(mixed):
    pos = np.array([f.position for f in mixed])
    vel = np.array([f.velocity for f in mixed])
    agl = pos[:, 2] - scene_ground_height("mixed", pos[:, :2])
    assert np.all(np.abs(agl - 40.0) < 2.0)
    np.testing.assert_allclose(np.hypot(vel[:, 0], vel[:, 1]), 8.0, rtol=1e-3)
    np.testing.assert_allclose(np.diff(pos, axis=0) * 10.0, (vel[1:] + vel[:-1]) / 2,
                               atol=0.05)
    # The body x axis points along the velocity (nose-down pitch aside).
    fwd = np.array([_rotation(f.orientation)[:, 0] for f in mixed])
    heading = vel[:, :2] / np.linalg.norm(vel[:, :2], axis=1, keepdims=True)
    fwd_xy = fwd[:, :2] / np.linalg.norm(fwd[:, :2], axis=1, keepdims=True)
    assert np.all(np.sum(heading * fwd_xy, axis=1) > 0.999)


# --------------------------------------------------------------------------- returns, intensity


def test_vegetation_gives_multiple_returns():
    p = _points(_flight(scene="forest", duration=1.0, points_per_frame=20_000))
    rn, nr = p["return_number"], p["number_of_returns"]
    assert np.all((rn >= 1) & (rn <= nr) & (nr <= 5))
    veg = np.isin(p["classification"], VEGETATION)
    assert np.mean(nr[veg] > 1) > 0.3
    ground = p["classification"] == 2
    assert np.any(ground & (rn > 1) & (rn == nr))   # ground seen through the canopy
    # Echoes of a pulse come in order: return_number counts up by one.
    start = rn == 1
    assert np.all(rn[~start] == rn[np.flatnonzero(~start) - 1] + 1)
    # And each pulse has exactly number_of_returns echoes.
    first = np.flatnonzero(start)
    sizes = np.diff(np.r_[first, len(p)])
    assert np.array_equal(sizes, nr[first])


def test_intensity_by_material(mixed):
    p = _points(mixed)
    cls = p["classification"]
    single = p["number_of_returns"] == 1
    mean = {c: float(p["intensity"][(cls == c) & single].mean()) / 65535.0
            for c in (2, 6, 14, 15)}
    mean[5] = float(p["intensity"][cls == 5].mean()) / 65535.0
    assert 0.2 <= mean[2] <= 0.4
    assert mean[5] < mean[2] < mean[6]
    wire = p["intensity"][cls == 14].mean() / 65535.0
    assert wire < mean[5]
    assert p["intensity"].min() >= 0 and p["intensity"].max() <= 65535


# --------------------------------------------------------------------------- laziness


def test_memory_stays_flat_over_a_long_lazy_flight():
    settings = SimSettings(scene="mixed", duration=3600.0, points_per_frame=3000)
    frames = simulate_flight(settings)       # one hour: only frames asked for are made
    for _ in itertools.islice(frames, 20):
        pass
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for k, frame in enumerate(itertools.islice(frames, 300)):
            if k == 50:
                early = tracemalloc.get_traced_memory()[0]
        late = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert late - early < 256 * 1024, (base, early, late)
    assert frame.stamp == pytest.approx(31.9)


def test_scene_info_and_dataclasses_are_frozen():
    info = scene_info(SimSettings())
    assert info.name == "mixed" and len(info.towers) >= 5 and len(info.spans) >= 4
    assert info.n_trees > 100 and info.n_buildings > 5 and info.n_poles > 5
    assert info.path_length > 10_000.0       # a 30-minute flight needs no repeat
    with pytest.raises(dataclasses.FrozenInstanceError):
        SimSettings().scene = "urban"  # type: ignore[misc]
