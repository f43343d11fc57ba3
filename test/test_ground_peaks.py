"""Peaks in the hybrid ground filter (_peak_points): on sparse scans a single low bush
point that the band lets in leaves the ground; hillsides, ridges and flat ground stay."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.core.ground import HybridSettings, morphological_ground


def _hills_with_bushes(seed: int = 0, spacing: float = 2.4):
    """(N, 3) centred points at the ISPRS sparse samples' spacing on a gentle hillside
    with a swell, and (N,) bool bush: 30 single points 0.45 m above the ground."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, 120.0, spacing)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = x + rng.uniform(-0.3, 0.3, x.size)
    y = y + rng.uniform(-0.3, 0.3, y.size)
    ground_z = 0.02 * x + 0.5 * np.sin(y / 20.0)
    z = ground_z + rng.normal(0.0, 0.03, x.size)
    bush = np.zeros(x.size, bool)
    bush[::83] = True  # 30 points, each more than 10 m from the next
    z[bush] += 0.45
    pts = np.column_stack([x, y, z])
    return pts - pts.mean(axis=0), bush


def test_single_raised_points_leave_the_ground_and_the_hills_stay():
    pts, bush = _hills_with_bushes()
    ground, _ = morphological_ground(pts, HybridSettings())
    assert not ground[bush].any()
    assert ground[~bush].mean() > 0.99
    # Without the peak test the band (0.5 m + slope) takes them all.
    plain, _ = morphological_ground(pts, HybridSettings(peak_window=0))
    assert plain[bush].all()


def test_no_peak_test_on_dense_scans():
    pts, _ = _hills_with_bushes(spacing=0.3)
    on, _ = morphological_ground(pts, HybridSettings())
    off, _ = morphological_ground(pts, HybridSettings(peak_window=0))
    assert np.array_equal(on, off)
