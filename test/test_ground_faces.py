"""Cliff faces in the hybrid ground filter (_face_points): points on a steep face between
two ground levels are ground on sparse scans; trees on a hillside are not."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.core.ground import HybridSettings, morphological_ground


def _cliff_and_hill(seed: int = 0, spacing: float = 2.4) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """(N, 3) centred points at the ISPRS sparse samples' spacing, (N,) bool face and (N,)
    bool tree: a floor, a 3:1 cliff face rising 12 m over 4 m (x 50-54 m) to a plateau;
    beside it a 1:5 hillside with three 9 m trees on it."""
    rng = np.random.default_rng(seed)
    g = np.arange(0.0, 120.0, spacing)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    x = x + rng.uniform(-0.3, 0.3, x.size)
    y = y + rng.uniform(-0.3, 0.3, y.size)
    cliff = np.clip(3.0 * (x - 50.0), 0.0, 12.0)
    hill = np.where(y > 60, 0.2 * np.clip(x - 60.0, 0.0, None), 0.0)
    ground_z = np.where(y > 60, hill, cliff)
    z = ground_z + rng.normal(0.0, 0.05, x.size)
    tree = np.zeros(x.size, bool)
    for cx, cy in ((80.0, 80.0), (95.0, 100.0), (105.0, 75.0)):
        crown = np.hypot(x - cx, y - cy) < 3.0
        z[crown] = ground_z[crown] + rng.uniform(5.0, 9.0, crown.sum())
        tree |= crown
    face = (y <= 60) & (x > 50.5) & (x < 53.5)
    pts = np.column_stack([x, y, z])
    return pts - pts.mean(axis=0), face, tree


def test_a_cliff_face_is_ground_and_trees_on_a_hillside_are_not():
    pts, face, tree = _cliff_and_hill()
    ground, _ = morphological_ground(pts, HybridSettings())
    assert face.sum() > 25
    assert ground[face].mean() > 0.9
    assert not ground[tree].any()
    assert ground[~face & ~tree].mean() > 0.99
    # Without the face test the opening cuts the face (the answer above is the test's).
    plain, _ = morphological_ground(pts, HybridSettings(face_radius=0))
    assert plain[face].mean() < 0.8
    assert not plain[tree].any()


def test_no_face_test_on_dense_scans():
    """On dense scans (median ground density over `dense_from`) the test is off."""
    pts, face, tree = _cliff_and_hill(spacing=0.3)
    on, _ = morphological_ground(pts, HybridSettings())
    off, _ = morphological_ground(pts, HybridSettings(face_radius=0))
    assert np.array_equal(on, off)
    assert not on[tree].any()
