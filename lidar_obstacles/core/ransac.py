"""Plane RANSAC with the robust eigenvalue fit (seed 004, section 1.3).

The plane is ax + by + cz = d with a² + b² + c² = 1 (total least squares: error in x, y
and z). Hypotheses are drawn in batches as arrays and scored in one matrix product; the
trial count adapts to the best inlier ratio w found so far, k = log(1-p) / log(1-w³).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar_obstacles.core.arrays import column_mean, row_norm

# The seed of the hypotheses' draws when the caller gives no generator: fixed, so the same
# points give the same plane in every run (the ground filter and the obstacle detector
# pass their own, from their config's seed).
RANSAC_SEED = 0


@dataclass(frozen=True)
class Plane:
    """normal: (3,) unit vector with normal[2] >= 0; d: offset (m), normal·p = d."""

    normal: np.ndarray
    d: float

    def distance(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) signed distance in metres, positive above (along the normal)."""
        return xyz @ self.normal - self.d


@dataclass(frozen=True)
class RansacResult:
    """plane: the best plane (refitted on its inliers when that keeps as many), None when
    there was none (fewer than 3 points, or no hypothesis within the tilt limit). inliers:
    (N,) bool, within the distance threshold of it. trials: hypotheses drawn.
    required_trials: the adaptive count k the best inlier ratio asked for (0 for fewer than
    3 points)."""

    plane: Plane | None
    inliers: np.ndarray  # (N,) bool
    trials: int
    required_trials: int


def fit_plane_eigen(xyz: np.ndarray) -> Plane | None:
    """Total-least-squares plane: the normal is the eigenvector of the smallest eigenvalue
    of the points' covariance. None for fewer than 3 points or a degenerate (collinear) set.

    xyz: (N, 3) float64 points, metres. Returns a Plane with normal (3,) unit vector
    (normal[2] >= 0) and d in metres (normal . p = d), in the points' own frame.
    """
    if len(xyz) < 3:
        return None
    centre = column_mean(xyz)
    cov = np.cov((xyz - centre).T)
    w, v = np.linalg.eigh(cov)
    if w[1] <= 1e-12 * max(w[2], 1e-300):
        return None  # collinear or coincident: no unique plane
    n = v[:, 0]
    if n[2] < 0:
        n = -n
    return Plane(n, float(n @ centre))


def required_trials(inlier_ratio: float, probability: float, sample_size: int = 3) -> int:
    """k = log(1-p) / log(1-w^n), at least 1."""
    w_n = inlier_ratio ** sample_size
    if w_n >= 1.0:
        return 1
    if w_n <= 0.0:
        return 2**31 - 1
    return max(1, math.ceil(math.log(1.0 - probability) / math.log(1.0 - w_n)))


def ransac_plane(xyz: np.ndarray, *, distance_threshold: float, probability: float = 0.99,
                 max_trials: int = 1000,
                 rng: np.random.Generator | int | None = RANSAC_SEED,
                 max_tilt_deg: float | None = None, batch: int = 64) -> RansacResult:
    """Best plane of (N, 3) points by inlier count, refitted on its inliers.

    xyz: (N, 3) float64 points, metres. distance_threshold: metres; a point is an inlier
    when its distance to the plane is below it. max_tilt_deg: degrees; only planes whose
    normal is within this angle of vertical (ground, roofs) are hypotheses. rng: the
    generator (or seed) of the samples; None is RANSAC_SEED as well. Deterministic for a
    given rng.
    """
    rng = np.random.default_rng(RANSAC_SEED if rng is None else rng)
    n = len(xyz)
    if n < 3:
        return RansacResult(None, np.zeros(n, bool), 0, 0)
    centre = column_mean(xyz)
    pts = xyz - centre  # centred: numerically safe with UTM coordinates
    best_count, best_n, best_d = -1, None, 0.0
    needed, trials = max_trials, 0
    min_nz = math.cos(math.radians(max_tilt_deg)) if max_tilt_deg is not None else -1.0
    while trials < min(needed, max_trials):
        m = min(batch, max_trials - trials)
        idx = rng.integers(0, n, size=(m, 3))
        a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
        normals = np.cross(b - a, c - a)
        norm = row_norm(normals)
        ok = norm > 1e-12
        normals = normals[ok] / norm[ok, None]
        normals *= np.where(normals[:, 2:3] < 0, -1.0, 1.0)
        ds = np.einsum("ij,ij->i", normals, a[ok])
        tilt_ok = normals[:, 2] >= min_nz
        normals, ds = normals[tilt_ok], ds[tilt_ok]
        trials += m
        if len(normals) == 0:
            continue
        counts = (np.abs(pts @ normals.T - ds) < distance_threshold).sum(axis=0)
        j = int(np.argmax(counts))
        if counts[j] > best_count:
            best_count, best_n, best_d = int(counts[j]), normals[j], float(ds[j])
            needed = required_trials(best_count / n, probability)
    if best_n is None:
        return RansacResult(None, np.zeros(n, bool), trials, needed)
    inliers = np.abs(pts @ best_n - best_d) < distance_threshold
    refit = fit_plane_eigen(pts[inliers])
    if refit is not None:
        refit_in = np.abs(refit.distance(pts)) < distance_threshold
        if refit_in.sum() >= inliers.sum():
            best_n, best_d, inliers = refit.normal, refit.d, refit_in
    plane = Plane(best_n, float(best_d + best_n @ centre))
    return RansacResult(plane, inliers, trials, needed)
