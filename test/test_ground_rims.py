"""Rim test of the hybrid ground filter (_rim_points) on a synthetic quarry with known answers."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.core.ground import HybridSettings, morphological_ground


def _quarry(seed: int = 0, spacing: float = 2.4) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) centred points at the ISPRS sparse samples' spacing and (N,) bool roof: a
    plateau (x < 50 m), a 1:4 cliff down 10 m to a 22.5 m wide terrace, another cliff down
    10 m to the floor, and on the floor a 24 x 24 m flat-roofed building 10 m high."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, 160.0, spacing)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = x + rng.uniform(-0.3, 0.3, x.size)
    y = y + rng.uniform(-0.3, 0.3, y.size)
    z = np.where(x < 50, 12.0, np.where(x < 52.5, 12 - 4 * (x - 50), np.where(
        x < 75, 2.0, np.where(x < 77.5, 2 - 4 * (x - 75), -8.0))))
    z = z + 0.02 * y + rng.normal(0.0, 0.05, x.size)
    roof = (x > 110) & (x < 134) & (y > 60) & (y < 84)
    z = np.where(roof, 2.0 + 0.02 * y, z)  # the floor's level + 10 m
    pts = np.column_stack([x, y, z])
    return pts - pts.mean(axis=0), roof


def test_rims_stay_ground_and_a_flat_roof_stays_object():
    pts, roof = _quarry()
    x = pts[:, 0] - pts[:, 0].min()
    rims = ((x > 46) & (x < 50.5)) | ((x > 71) & (x < 75.2))  # the last 4 m before each drop
    ground, _ = morphological_ground(pts, HybridSettings())
    assert ground[rims].mean() > 0.97
    assert not ground[roof].any()
    assert ground[~roof].mean() > 0.99
    # Without the rim test the opening cuts the rims (the answer above is the test's doing).
    plain, _ = morphological_ground(pts, HybridSettings(rim_window=0))
    assert plain[rims].mean() < 0.9
    assert not plain[roof].any()
