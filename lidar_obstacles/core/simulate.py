"""Deterministic, labelled synthetic UAV LiDAR flight (the package's embedded default).

A scene is built once, per (scene, seed), from analytic primitives over a ~1 km square:
a terrain height field (slope, smooth hills, metre-scale relief), convex buildings with
flat, gable or hip roofs, trees (ellipsoid crowns that are semi-transparent to the beam,
cylindrical trunks), bushes and low cover, lattice transmission towers made of thin
members, catenary conductors between the towers' arms, and poles. A UAV flies a closed
loop over it (lawn-mower, or a racetrack along the power line for ``corridor``) at a set
height above the terrain and speed; longer flights repeat the loop. It carries a 2-D
scanning LiDAR looking down (90 x 40 deg by default); every ``1 / rate`` s one cloud is
ray-cast, vectorised over all pulses:

- every pulse meets the terrain (Newton steps on the height field) and the nearest solid
  primitive (roof, wall, trunk, pole) ends it;
- crowns and bushes give volumetric echoes (exponential free path in the foliage), wires
  and tower members partial echoes, after which the pulse goes on with some probability:
  vegetation and wires give multiple returns (``return_number`` / ``number_of_returns``)
  with the ground below them; an echo closer to the ground than the pulse separation
  merges with it (low cover hides the ground);
- range noise, a few outliers (class 7) far above or below the surface, and intensity by
  material, incidence angle and shared pulse energy.

Per frame, primitives are culled by a spatial grid and by projecting their bounding
boxes into the sensor's tangent plane, where the pulses are bucketed; only (pulse,
primitive) pairs that can meet are intersected.

Labels are ASPRS codes: 2 ground, 3/4/5 vegetation by height above the true terrain
(< 0.5, 0.5-2, >= 2 m), 6 building, 7 noise, 14 wire conductor, 15 transmission tower
(members and insulators), 1 unclassified (poles). ``point_id`` is unique and increasing
over the flight. Frames are generated lazily: memory does not grow with the duration.
Pulse origins move along the trajectory within a frame, so map-frame clouds are exact
(deskewed) and sensor-frame clouds are ``R^T (p_map - t)`` with the frame's pose.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from lidar_obstacles.core.arrays import points_xyz
from lidar_obstacles.errors import ConfigError

SCENES = ("mixed", "corridor", "urban", "forest")
FRAMES = ("map", "sensor")

#: Layout of ``SimFrame.points`` (packed, 23 bytes per point).
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                        ("return_number", "u1"), ("number_of_returns", "u1"),
                        ("classification", "u1"), ("point_id", "<u4")])

#: Full scale of ``intensity`` (16-bit scanners).
INTENSITY_SCALE = 65535.0

# ASPRS classes.
UNCLASSIFIED, GROUND, LOW_VEG, MEDIUM_VEG, HIGH_VEG = 1, 2, 3, 4, 5
BUILDING, NOISE, WIRE, TOWER = 6, 7, 14, 15
_VEGETATION = 0  # internal: class decided from the height above ground

# Reflectance (fraction of full-scale intensity) by material.
_R_GROUND, _R_VEG, _R_TRUNK, _R_WALL = 0.30, 0.12, 0.18, 0.40
_R_WIRE, _R_TOWER, _R_POLE = 0.09, 0.35, 0.24

# Primitive kinds.
_POLY, _ELL, _CYL, _SEG = 0, 1, 2, 3

_MAX_PLANES = 9           # walls 4 + floor + hip roof 4
_TERRAIN_RES = 1.0        # m per cell of the terrain grid
_TERRAIN_HALF = 640.0     # terrain grid covers [-h, h]^2, m
_CONTENT_HALF = 540.0     # objects are placed inside [-h, h]^2, m
_CELL = 20.0              # m, spatial grid for culling
_CULL_MARGIN = 0.6        # m, bounding boxes grow by this (pulse origins move in a frame)
_PULSE_SEPARATION = 0.8   # m, two echoes of one pulse are at least this far apart
_ECHO_CONTINUE = {"veg": 0.6, "wire": 0.95, "tower": 0.85}


@dataclass(frozen=True)
class SimSettings:
    """What to simulate. Invalid values raise :class:`ConfigError` at construction.

    The scene and the flight depend only on ``scene`` and ``seed``; every other field
    changes the flight or the scanner.
    """

    scene: str = "mixed"
    seed: int = 0
    duration: float = 20.0          # s
    rate: float = 10.0              # clouds per second, Hz
    altitude: float = 40.0          # m above the terrain
    speed: float = 8.0              # m/s over ground
    points_per_frame: int = 50_000  # target echoes per cloud (the pulse count adapts)
    frame: str = "map"              # "map" or "sensor" (points relative to the UAV pose)
    fov_across: float = 90.0        # deg, full scan angle across track
    fov_along: float = 40.0         # deg, full scan angle along track
    range_noise: float = 0.025      # m, standard deviation along the beam
    outlier_rate: float = 2e-4      # fraction of pulses that give one noise echo
    wire_radius: float = 0.10       # m, effective radius of conductors (beam footprint)
    max_returns: int = 5            # echoes per pulse at most

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ConfigError(f"scene: unknown scene {self.scene!r}, expected one of "
                              f"{', '.join(SCENES)}")
        if self.frame not in FRAMES:
            raise ConfigError(f"frame: {self.frame!r} is not one of {', '.join(FRAMES)}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) \
                or not 0 <= self.seed < 2**63:
            raise ConfigError(f"seed: {self.seed!r} is not a non-negative integer")
        if isinstance(self.points_per_frame, bool) \
                or not isinstance(self.points_per_frame, (int, np.integer)):
            raise ConfigError(f"points_per_frame: {self.points_per_frame!r} is not an integer")
        if isinstance(self.max_returns, bool) \
                or not isinstance(self.max_returns, (int, np.integer)):
            raise ConfigError(f"max_returns: {self.max_returns!r} is not an integer")
        ranges = {"duration": (1e-3, 1e6), "rate": (0.1, 100.0), "altitude": (5.0, 150.0),
                  "speed": (0.0, 40.0), "points_per_frame": (100, 1_000_000),
                  "fov_across": (1.0, 120.0), "fov_along": (1.0, 60.0),
                  "range_noise": (0.0, 1.0), "outlier_rate": (0.0, 0.05),
                  "wire_radius": (0.005, 0.5), "max_returns": (1, 7)}
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(value) or not lo <= value <= hi:
                raise ConfigError(f"{name}: {value!r} is outside [{lo:g}, {hi:g}]")
        # Echo counts stay within a few % of the target (the pulse count adapts); 1.25
        # leaves room, so that point_id (uint32) cannot wrap.
        frames = math.ceil(self.duration * self.rate)
        if frames * self.points_per_frame * 1.25 >= 2**32:
            raise ConfigError(f"duration: {self.duration:g} s at {self.rate:g} Hz and "
                              f"{self.points_per_frame} points per frame overflows the "
                              "uint32 point_id")


@dataclass(frozen=True)
class SimFrame:
    """One simulated cloud and the UAV pose at its stamp."""

    stamp: float            # s since the start of the flight
    points: np.ndarray      # (N,) POINT_DTYPE; x y z in map (or sensor) frame, metres
    position: np.ndarray    # (3,) float64, UAV position in map, m
    orientation: np.ndarray  # (4,) float64, quaternion x y z w rotating sensor -> map
    velocity: np.ndarray    # (3,) float64, m/s in map


@dataclass(frozen=True)
class SceneInfo:
    """What a scene contains, for tests and reports."""

    name: str
    seed: int
    extent: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax of the objects, m
    towers: np.ndarray          # (T, 3) float64, tower base centres, m
    tower_heights: np.ndarray   # (T,) float64, m above the base
    spans: np.ndarray           # (S, 2) int, tower indices joined by conductors
    n_trees: int
    n_shrubs: int
    n_buildings: int
    n_poles: int
    path_length: float          # m, one loop of the flight path


# --------------------------------------------------------------------------- terrain


class _Terrain:
    """Height field z = f(x, y): bilinear interpolation of a 1 m grid."""

    def __init__(self, z: np.ndarray, origin: float, res: float,
                 smooth: "functools.partial[np.ndarray]", reflect: np.ndarray) -> None:
        self.z = z                    # (n, n) float64, row = y, col = x
        self.flat = z.ravel()
        self.n = z.shape[0]
        self.origin = origin          # x and y of cell (0, 0), m
        self.res = res
        self.smooth = smooth          # analytic large-scale part, for the flight height
        self.reflect = reflect        # (m, m) float32 ground reflectance, 8 m cells

    def _cells(self, x: np.ndarray, y: np.ndarray):
        fx = (x - self.origin) / self.res
        fy = (y - self.origin) / self.res
        ix = np.clip(np.floor(fx), 0, self.n - 2).astype(np.intp)
        iy = np.clip(np.floor(fy), 0, self.n - 2).astype(np.intp)
        tx = np.clip(fx - ix, 0.0, 1.0)
        ty = np.clip(fy - iy, 0.0, 1.0)
        k = iy * self.n + ix
        f = self.flat
        return f[k], f[k + 1], f[k + self.n], f[k + self.n + 1], tx, ty

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        z00, z10, z01, z11, tx, ty = self._cells(x, y)
        return (z00 + (z10 - z00) * tx) * (1 - ty) + (z01 + (z11 - z01) * tx) * ty

    def height_grad(self, x: np.ndarray, y: np.ndarray):
        z00, z10, z01, z11, tx, ty = self._cells(x, y)
        a = z10 - z00
        b = z11 - z01
        z = (z00 + a * tx) * (1 - ty) + (z01 + b * tx) * ty
        gx = (a * (1 - ty) + b * ty) / self.res
        gy = ((z01 - z00) * (1 - tx) + (z11 - z10) * tx) / self.res
        return z, gx, gy

    def ground_reflectance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        m = self.reflect.shape[0]
        ix = np.clip(((x - self.origin) / 8.0).astype(np.intp), 0, m - 1)
        iy = np.clip(((y - self.origin) / 8.0).astype(np.intp), 0, m - 1)
        return self.reflect[iy, ix]


def _smooth_terrain(x: np.ndarray, y: np.ndarray, *, slope: np.ndarray,
                    hills: np.ndarray) -> np.ndarray:
    """Large-scale terrain: a plane plus Gaussian hills (H, 4: cx, cy, amplitude, sigma)."""
    z = slope[0] * x + slope[1] * y
    for cx, cy, amp, sigma in hills:
        z = z + amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2.0 * sigma * sigma))
    return z


def _make_terrain(rng: np.random.Generator, *, slope_max: float, n_hills: int,
                  amp: tuple[float, float], sigma: tuple[float, float],
                  detail: float) -> _Terrain:
    angle = rng.uniform(0, 2 * np.pi)
    slope = rng.uniform(0.3, 1.0) * slope_max * np.array([np.cos(angle), np.sin(angle)])
    hills = np.column_stack([rng.uniform(-560, 560, n_hills), rng.uniform(-560, 560, n_hills),
                             rng.uniform(*amp, n_hills) * rng.choice([-0.6, 1.0], n_hills),
                             rng.uniform(*sigma, n_hills)])
    smooth = functools.partial(_smooth_terrain, slope=slope, hills=hills)
    n = int(round(2 * _TERRAIN_HALF / _TERRAIN_RES)) + 1
    axis = -_TERRAIN_HALF + _TERRAIN_RES * np.arange(n)
    gx, gy = np.meshgrid(axis, axis)
    z = smooth(gx, gy)
    # Fine relief (metre-scale bumps) on top of the hills: filtered white noise.
    coarse = ndimage.gaussian_filter(rng.standard_normal((n // 4 + 1, n // 4 + 1)), 2.0)
    coarse *= detail / max(coarse.std(), 1e-9)
    z += ndimage.zoom(coarse, 4.0, order=3)[:n, :n]
    m = int(2 * _TERRAIN_HALF / 8.0) + 1
    refl = ndimage.gaussian_filter(rng.standard_normal((m, m)), 3.0)
    refl = _R_GROUND + 0.04 * refl / max(refl.std(), 1e-9)
    return _Terrain(np.ascontiguousarray(z), -_TERRAIN_HALF, _TERRAIN_RES, smooth,
                    refl.astype(np.float32))


# --------------------------------------------------------------------------- scene


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _Builder:
    """Collects primitives, then freezes them into arrays and a culling grid."""

    def __init__(self, terrain: _Terrain) -> None:
        self.terrain = terrain
        self.planes: list[np.ndarray] = []     # (9, 4) each
        self.plane_refl: list[np.ndarray] = []
        self.poly_box: list[np.ndarray] = []   # (2, 3) each
        self.ell: list[np.ndarray] = []        # (n, 7): c3, r3, lambda
        self.cyl: list[np.ndarray] = []        # (n, 7): x, y, z0, z1, r, cls, refl
        self.seg: list[np.ndarray] = []        # (n, 9): p0, p1, r, cls, refl
        self.n_trees = self.n_shrubs = self.n_poles = 0
        self.towers: list[np.ndarray] = []
        self.tower_heights: list[float] = []
        self.spans: list[tuple[int, int]] = []

    # -- buildings
    def add_building(self, cx: float, cy: float, yaw: float, length: float, width: float,
                     wall: float, roof: str, pitch_h: float, roof_refl: float) -> None:
        hx, hy = length / 2, width / 2
        rot = _rot_z(yaw)
        corners = (rot[:2, :2] @ np.array([[hx, hx, -hx, -hx], [hy, -hy, hy, -hy]])).T
        corners += (cx, cy)
        ground = self.terrain.height(corners[:, 0], corners[:, 1])
        z_floor = ground.min() - 1.0
        z_eave = ground.max() + wall
        z_top = z_eave + (pitch_h if roof != "flat" else 0.0)
        # (nx, ny, nz, d, reflectance): the half-space nx x + ny y + nz z <= d
        local: list[tuple[float, float, float, float, float]] = [
                 (1, 0, 0, hx, _R_WALL), (-1, 0, 0, hx, _R_WALL), (0, 1, 0, hy, _R_WALL),
                 (0, -1, 0, hy, _R_WALL), (0, 0, -1, -z_floor, _R_WALL)]
        if roof == "flat":
            local.append((0, 0, 1, z_eave, roof_refl))
        else:
            h = pitch_h
            local += [(0, h, hy, h * hy + hy * z_eave, roof_refl),
                      (0, -h, hy, h * hy + hy * z_eave, roof_refl)]
            if roof == "hip":
                local += [(h, 0, hy, h * hx + hy * z_eave, roof_refl),
                          (-h, 0, hy, h * hx + hy * z_eave, roof_refl)]
        planes = np.zeros((_MAX_PLANES, 4))
        planes[:, 3] = 1.0      # padding planes 0 . p <= 1 never cut
        refl = np.full(_MAX_PLANES, _R_WALL)
        for i, (nx, ny, nz, d, r) in enumerate(local):
            n = np.array([nx, ny, nz], float)
            norm = np.linalg.norm(n)
            nw = rot @ (n / norm)
            planes[i, :3] = nw
            planes[i, 3] = d / norm + nw[0] * cx + nw[1] * cy
            refl[i] = r
        self.planes.append(planes)
        self.plane_refl.append(refl)
        lo = np.array([corners[:, 0].min(), corners[:, 1].min(), z_floor])
        hi = np.array([corners[:, 0].max(), corners[:, 1].max(), z_top])
        self.poly_box.append(np.stack([lo, hi]))

    # -- vegetation
    def add_trees(self, x: np.ndarray, y: np.ndarray, height: np.ndarray,
                  rng: np.random.Generator) -> None:
        n = len(x)
        if n == 0:
            return
        g = self.terrain.height(x, y)
        conifer = rng.random(n) < 0.35
        r = np.where(conifer, rng.uniform(0.14, 0.2, n), rng.uniform(0.22, 0.36, n)) * height
        rz = np.where(conifer, rng.uniform(0.34, 0.42, n), rng.uniform(0.28, 0.38, n)) * height
        r = np.maximum(r, 0.8)
        cz = g + height - rz
        lam = np.where(conifer, 0.7, 0.55)
        self.ell.append(np.column_stack([x, y, cz, r * rng.uniform(0.9, 1.1, n),
                                         r * rng.uniform(0.9, 1.1, n), rz, lam]))
        trunk_r = 0.08 + 0.012 * height
        self.cyl.append(np.column_stack([x, y, g - 0.3, cz, trunk_r,
                                         np.full(n, _VEGETATION), np.full(n, _R_TRUNK)]))
        self.n_trees += n

    def add_shrubs(self, x: np.ndarray, y: np.ndarray, height: np.ndarray,
                   rng: np.random.Generator) -> None:
        n = len(x)
        if n == 0:
            return
        g = self.terrain.height(x, y)
        r = rng.uniform(0.5, 1.6, n)
        rz = height / 2
        self.ell.append(np.column_stack([x, y, g + rz - 0.05, r, r * rng.uniform(0.7, 1.0, n),
                                         rz, np.full(n, 1.8)]))
        self.n_shrubs += n

    # -- poles
    def add_poles(self, x: np.ndarray, y: np.ndarray, height: np.ndarray) -> None:
        n = len(x)
        if n == 0:
            return
        g = self.terrain.height(x, y)
        self.cyl.append(np.column_stack([x, y, g - 0.5, g + height, np.full(n, 0.16),
                                         np.full(n, UNCLASSIFIED), np.full(n, _R_POLE)]))
        self.n_poles += n

    # -- power lines
    def add_power_line(self, route: np.ndarray, height: np.ndarray) -> None:
        """Lattice towers at ``route`` (T, 2) with ``height`` (T,) m, conductors between."""
        route = np.asarray(route, float)
        t = len(route)
        dirs = np.diff(route, axis=0)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        along = np.vstack([dirs[:1], dirs[:-1] + dirs[1:], dirs[-1:]])
        yaws = np.arctan2(along[:, 1], along[:, 0])
        base_z = self.terrain.height(route[:, 0], route[:, 1])
        height = np.asarray(height, float).copy()
        # Every conductor must clear the ground by 12 m: over a dip, string the span
        # tighter first (less sag), and raise its towers only if that is not enough,
        # so that wires stay within 10-40 m above ground on most terrain.
        sags = np.full(t - 1, _SAGS[0])
        for _ in range(4):
            deficit = np.zeros(t)
            for i in range(t - 1):
                a = _to_world(_tower_attachments(height[i]), route[i], base_z[i], yaws[i])
                b = _to_world(_tower_attachments(height[i + 1]), route[i + 1],
                              base_z[i + 1], yaws[i + 1])
                for sag in _SAGS:
                    clearance = min(self._clearance(a[k], b[k], sag) for k in range(len(a)))
                    if clearance >= 12.0:
                        break
                sags[i] = sag
                need = max(0.0, 12.0 - clearance)
                deficit[i] = max(deficit[i], need)
                deficit[i + 1] = max(deficit[i + 1], need)
            if not deficit.any():
                break
            height += deficit + 0.2
        offset = len(self.towers)
        for i in range(t):
            p0, p1, radius = _tower_members(height[i])
            rot = _rot_z(yaws[i])
            shift = np.array([route[i, 0], route[i, 1], base_z[i]])
            p0 = p0 @ rot.T + shift
            p1 = p1 @ rot.T + shift
            self.seg.append(np.column_stack([p0, p1, radius, np.full(len(p0), TOWER),
                                             np.full(len(p0), _R_TOWER)]))
            self.towers.append(shift)
            self.tower_heights.append(float(height[i]))
        for i in range(t - 1):
            a = _to_world(_tower_attachments(height[i]), route[i], base_z[i], yaws[i])
            b = _to_world(_tower_attachments(height[i + 1]), route[i + 1], base_z[i + 1],
                          yaws[i + 1])
            for k in range(len(a)):
                pts = _catenary(a[k], b[k], sag_ratio=_wire_sag(sags[i], k, len(a)))
                # Wire radius is a scanner setting: 0 here, applied at intersection time.
                self.seg.append(np.column_stack([pts[:-1], pts[1:], np.zeros(len(pts) - 1),
                                                 np.full(len(pts) - 1, WIRE),
                                                 np.full(len(pts) - 1, _R_WIRE)]))
            self.spans.append((offset + i, offset + i + 1))

    def _clearance(self, a: np.ndarray, b: np.ndarray, sag: float) -> float:
        pts = _catenary(a, b, sag_ratio=sag)
        return float((pts[:, 2] - self.terrain.height(pts[:, 0], pts[:, 1])).min())

    # -- freeze
    def finish(self, name: str, seed: int, path: "_Path") -> "_Scene":
        planes = np.array(self.planes).reshape(-1, _MAX_PLANES, 4)
        plane_refl = np.array(self.plane_refl).reshape(-1, _MAX_PLANES)
        ell = np.concatenate(self.ell) if self.ell else np.zeros((0, 7))
        cyl = np.concatenate(self.cyl) if self.cyl else np.zeros((0, 7))
        seg = np.concatenate(self.seg) if self.seg else np.zeros((0, 9))
        boxes = [np.array(self.poly_box).reshape(-1, 2, 3)]
        boxes.append(np.stack([ell[:, :3] - ell[:, 3:6], ell[:, :3] + ell[:, 3:6]], axis=1))
        cyl_lo = np.column_stack([cyl[:, 0] - cyl[:, 4], cyl[:, 1] - cyl[:, 4], cyl[:, 2]])
        cyl_hi = np.column_stack([cyl[:, 0] + cyl[:, 4], cyl[:, 1] + cyl[:, 4], cyl[:, 3]])
        boxes.append(np.stack([cyl_lo, cyl_hi], axis=1))
        r = seg[:, 6:7]
        boxes.append(np.stack([np.minimum(seg[:, 0:3], seg[:, 3:6]) - r,
                               np.maximum(seg[:, 0:3], seg[:, 3:6]) + r], axis=1))
        counts = [len(planes), len(ell), len(cyl), len(seg)]
        kind = np.repeat(np.arange(4, dtype=np.int8), counts)
        index = np.concatenate([np.arange(c, dtype=np.int64) for c in counts])
        box = np.concatenate(boxes)
        grid = _CullGrid(box)
        return _Scene(name=name, seed=seed, terrain=self.terrain, planes=planes,
                      plane_refl=plane_refl.astype(np.float32),
                      ell_cols=tuple(np.ascontiguousarray(c) for c in np.column_stack(
                          [ell[:, :3], 1.0 / ell[:, 3:6], ell[:, 6]]).T),
                      cyl=cyl, seg=seg,
                      kind=kind, index=index, box=box, grid=grid, path=path,
                      towers=np.array(self.towers).reshape(-1, 3),
                      tower_heights=np.array(self.tower_heights),
                      spans=np.array(self.spans, dtype=np.int64).reshape(-1, 2),
                      n_trees=self.n_trees, n_shrubs=self.n_shrubs,
                      n_buildings=len(planes), n_poles=self.n_poles)


# Tower design: 3 cross-arm levels (below the top) with conductors on both sides,
# plus the earth wire on the peak.
_ARM_DROP = np.array([9.0, 5.0, 1.0])   # m below the body top
_ARM_HALF = np.array([5.5, 7.0, 5.0])   # m, arm length from the axis
_INSULATOR = 2.5                        # m


_SAGS = (0.032, 0.026, 0.02, 0.015)     # sag / span of the conductors, tried in turn


def _wire_sag(conductor_sag: float, k: int, n: int) -> float:
    """Sag ratio of wire k of n: the earth wire (last) is strung tighter."""
    return 0.8 * conductor_sag if k == n - 1 else conductor_sag


def _tower_attachments(height: float) -> np.ndarray:
    """(7, 3) conductor attachment points in the tower frame (x along the line)."""
    body_top = height - 3.0
    pts = []
    for side in (1.0, -1.0):
        for drop, half in zip(_ARM_DROP, _ARM_HALF):
            pts.append((0.0, side * half, body_top - drop - _INSULATOR))
    pts.append((0.0, 0.0, height))
    return np.array(pts)


def _to_world(local: np.ndarray, xy: np.ndarray, z: float, yaw: float) -> np.ndarray:
    return local @ _rot_z(yaw).T + np.array([xy[0], xy[1], z])


def _tower_members(height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Members of a lattice tower in its frame: p0, p1 (M, 3) and radius (M,), metres."""
    body_top = height - 3.0
    b0, b1 = max(2.5, 0.11 * height), 0.9
    z = body_top * np.linspace(0.0, 1.0, 9) ** 0.8
    b = b0 + (b1 - b0) * z / body_top
    p0: list[tuple[float, float, float]] = []
    p1: list[tuple[float, float, float]] = []
    rad: list[float] = []

    def member(a, c, r=0.07):
        p0.append(a)
        p1.append(c)
        rad.append(r)

    corners = [(1, 1), (1, -1), (-1, -1), (-1, 1)]
    for i in range(len(z) - 1):
        for k, (sx, sy) in enumerate(corners):
            member((sx * b[i], sy * b[i], z[i]), (sx * b[i + 1], sy * b[i + 1], z[i + 1]), 0.14)
            tx, ty = corners[(k + 1) % 4]
            member((sx * b[i + 1], sy * b[i + 1], z[i + 1]),
                   (tx * b[i + 1], ty * b[i + 1], z[i + 1]))
            member((sx * b[i], sy * b[i], z[i]), (tx * b[i + 1], ty * b[i + 1], z[i + 1]))
            member((tx * b[i], ty * b[i], z[i]), (sx * b[i + 1], sy * b[i + 1], z[i + 1]))
    for drop, half in zip(_ARM_DROP, _ARM_HALF):
        za = body_top - drop
        ba = b0 + (b1 - b0) * za / body_top
        for side in (1.0, -1.0):
            tip = (0.0, side * half, za)
            for across in (1.0, -1.0):
                member((across * ba, side * ba, za), tip)
                member((across * ba, side * ba, za + 1.5), tip)
            member(tip, (0.0, side * half, za - _INSULATOR), 0.12)
    for sx, sy in corners:
        member((sx * b1, sy * b1, body_top), (0.0, 0.0, height))
    return np.array(p0), np.array(p1), np.array(rad)


def _catenary(a: np.ndarray, b: np.ndarray, *, sag_ratio: float,
              step: float = 4.0) -> np.ndarray:
    """(K, 3) points of the catenary z = z0 + c (cosh((s - s0) / c) - 1) from a to b."""
    span = float(np.hypot(*(b[:2] - a[:2])))
    c = span / (8.0 * sag_ratio)   # parameter giving the wanted mid-span sag (flat wire)
    dz = b[2] - a[2]
    s0 = span / 2 - c * math.asinh(dz / (2 * c * math.sinh(span / (2 * c))))
    s = np.linspace(0.0, span, max(2, int(math.ceil(span / step)) + 1))
    z = a[2] + c * (np.cosh((s - s0) / c) - math.cosh(s0 / c))
    xy = a[:2] + np.outer(s / span, b[:2] - a[:2])
    return np.column_stack([xy, z])


class _CullGrid:
    """Bounding boxes bucketed into 20 m XY cells (CSR layout)."""

    def __init__(self, box: np.ndarray) -> None:
        lo = np.floor((box[:, 0, :2] + _TERRAIN_HALF) / _CELL).astype(np.int64)
        hi = np.floor((box[:, 1, :2] + _TERRAIN_HALF) / _CELL).astype(np.int64)
        self.n = int(2 * _TERRAIN_HALF / _CELL) + 1
        lo = np.clip(lo, 0, self.n - 1)
        hi = np.clip(hi, 0, self.n - 1)
        nx = hi[:, 0] - lo[:, 0] + 1
        ny = hi[:, 1] - lo[:, 1] + 1
        count = nx * ny
        prim = np.repeat(np.arange(len(box)), count)
        k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        cx = lo[prim, 0] + k % nx[prim]
        cy = lo[prim, 1] + k // nx[prim]
        cell = cy * self.n + cx
        order = np.argsort(cell, kind="stable")
        self.prims = prim[order]
        self.start = np.searchsorted(cell[order], np.arange(self.n * self.n + 1))

    def query(self, xmin: float, xmax: float, ymin: float, ymax: float) -> np.ndarray:
        """Indices of the primitives whose cells meet the rectangle (unique, sorted)."""
        c0 = np.clip(np.floor((np.array([xmin, ymin]) + _TERRAIN_HALF) / _CELL), 0,
                     self.n - 1).astype(np.int64)
        c1 = np.clip(np.floor((np.array([xmax, ymax]) + _TERRAIN_HALF) / _CELL), 0,
                     self.n - 1).astype(np.int64)
        rows = np.arange(c0[1], c1[1] + 1) * self.n
        lo = self.start[rows + c0[0]]
        hi = self.start[rows + c1[0] + 1]
        counts = hi - lo
        idx = np.repeat(lo - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
        return np.unique(self.prims[idx])


@dataclass
class _Scene:
    name: str
    seed: int
    terrain: _Terrain
    planes: np.ndarray       # (B, 9, 4): n . p <= d
    plane_refl: np.ndarray   # (B, 9)
    ell_cols: tuple          # 7 x (E,): centre x y z, 1 / radii, extinction 1/m
    cyl: np.ndarray          # (C, 7): x, y, z0, z1, radius, class, reflectance
    seg: np.ndarray          # (S, 9): p0, p1, radius, class, reflectance
    kind: np.ndarray         # (P,) primitive kind
    index: np.ndarray        # (P,) row in its kind's table
    box: np.ndarray          # (P, 2, 3) bounding boxes
    grid: _CullGrid
    path: "_Path"
    towers: np.ndarray
    tower_heights: np.ndarray
    spans: np.ndarray
    n_trees: int
    n_shrubs: int
    n_buildings: int
    n_poles: int


# --------------------------------------------------------------------------- flight path


class _Path:
    """A closed XY polyline with rounded corners (circular arcs), flown at constant speed.

    Pieces alternate arc, line, arc, line...; ``xy(s)`` evaluates any arc length s,
    wrapping around the loop, so flights of any duration repeat the loop.
    """

    def __init__(self, corners: np.ndarray, radius: float, start_xy: tuple[float, float]):
        corners = np.asarray(corners, float)
        n = len(corners)
        kind, origin, dirn, phi0, sweep, length = [], [], [], [], [], []
        exits, entries = [], []
        for i in range(n):
            p = corners[i]
            a = p - corners[i - 1]
            b = corners[(i + 1) % n] - p
            a /= np.linalg.norm(a)
            b /= np.linalg.norm(b)
            theta = math.acos(float(np.clip(a @ b, -1.0, 1.0)))
            d = radius * math.tan(theta / 2)          # corner to tangent point
            turn = 1.0 if a[0] * b[1] - a[1] * b[0] > 0 else -1.0
            start = p - a * d
            centre = start + radius * turn * np.array([-a[1], a[0]])
            entries.append(start)
            exits.append(p + b * d)
            kind.append(1)
            origin.append(centre)
            dirn.append(np.zeros(2))
            phi0.append(math.atan2(start[1] - centre[1], start[0] - centre[0]))
            sweep.append(turn * theta)
            length.append(radius * theta)
        for i in range(n):      # the straight legs between the arcs
            v = entries[(i + 1) % n] - exits[i]
            leg = float(np.linalg.norm(v))
            kind.insert(2 * i + 1, 0)
            origin.insert(2 * i + 1, exits[i])
            dirn.insert(2 * i + 1, v / max(leg, 1e-9))
            phi0.insert(2 * i + 1, 0.0)
            sweep.insert(2 * i + 1, 0.0)
            length.insert(2 * i + 1, leg)
        self.radius = radius
        self.kind = np.array(kind)
        self.origin = np.array(origin)
        self.dirn = np.array(dirn)
        self.phi0 = np.array(phi0)
        self.sweep = np.array(sweep)
        self.cum = np.concatenate([[0.0], np.cumsum(length)])
        self.length = float(self.cum[-1])
        probe = np.arange(0.0, self.length, 1.0)
        xy, _ = self.xy(probe, offset=0.0)
        self.s0 = float(probe[np.argmin(np.hypot(xy[:, 0] - start_xy[0],
                                                 xy[:, 1] - start_xy[1]))])

    def xy(self, s: np.ndarray, offset: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Position (K, 2) m and unit heading (K, 2) at arc length s (K,) m from the start."""
        s = (np.asarray(s, float) + (self.s0 if offset is None else offset)) % self.length
        i = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.kind) - 1)
        u = s - self.cum[i]
        line = self.kind[i] == 0
        pos = np.empty((len(s), 2))
        head = np.empty((len(s), 2))
        pos[line] = self.origin[i[line]] + self.dirn[i[line]] * u[line, None]
        head[line] = self.dirn[i[line]]
        arc = ~line
        sign = np.sign(self.sweep[i[arc]])
        phi = self.phi0[i[arc]] + sign * u[arc] / self.radius
        pos[arc] = self.origin[i[arc]] + self.radius * np.column_stack([np.cos(phi),
                                                                       np.sin(phi)])
        head[arc] = sign[:, None] * np.column_stack([-np.sin(phi), np.cos(phi)])
        return pos, head


def _lawnmower(x0: float, x1: float, y0: float, spacing: float, lines: int) -> np.ndarray:
    """Corners of a closed lawn-mower loop: ``lines`` (even) passes along x, then back."""
    corners = []
    for k in range(lines):
        y = y0 + k * spacing
        corners += [(x0, y), (x1, y)] if k % 2 == 0 else [(x1, y), (x0, y)]
    corners += [(x0 - spacing, y0 + (lines - 1) * spacing), (x0 - spacing, y0)]
    return np.array(corners)


# --------------------------------------------------------------------------- scenes


def _jittered(rng: np.random.Generator, spacing: float, keep: float,
              half: float = _CONTENT_HALF) -> np.ndarray:
    """(K, 2) points on a jittered grid over [-half, half]^2, each kept with ``keep``."""
    axis = np.arange(-half, half, spacing) + spacing / 2
    gx, gy = np.meshgrid(axis, axis)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    pts += rng.uniform(-0.45, 0.45, pts.shape) * spacing
    return pts[rng.random(len(pts)) < keep]


def _in_discs(pts: np.ndarray, discs: np.ndarray) -> np.ndarray:
    """Mask of the points inside any disc (K, 3: cx, cy, r)."""
    if len(discs) == 0 or len(pts) == 0:
        return np.zeros(len(pts), bool)
    tree = cKDTree(discs[:, :2])
    hits = tree.query_ball_point(pts, r=float(discs[:, 2].max()))
    inside = np.zeros(len(pts), bool)
    counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
    if counts.sum():
        p = np.repeat(np.arange(len(pts)), counts)
        d = np.concatenate([np.asarray(h, np.int64) for h in hits if h])
        ok = np.hypot(*(pts[p] - discs[d, :2]).T) < discs[d, 2]
        inside[p[ok]] = True
    return inside


def _near_polyline(pts: np.ndarray, line: np.ndarray, dist: float) -> np.ndarray:
    """Mask of the points within ``dist`` m of the polyline (K, 2)."""
    near = np.zeros(len(pts), bool)
    for a, b in zip(line[:-1], line[1:]):
        ab = b - a
        t = np.clip(((pts - a) @ ab) / (ab @ ab), 0.0, 1.0)
        near |= np.hypot(*(pts - a - t[:, None] * ab).T) < dist
    return near


def _tree_heights(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    return lo + (hi - lo) * rng.beta(2.2, 1.8, n)


def _shrub_heights(rng: np.random.Generator, n: int) -> np.ndarray:
    """Half low cover (grass tufts, crops: class 3), half bushes (mostly class 4)."""
    return np.where(rng.random(n) < 0.5, rng.uniform(0.25, 0.6, n), rng.uniform(0.7, 2.3, n))


def _add_village(b: _Builder, rng: np.random.Generator, cx: float, cy: float, nx: int,
                 ny: int, lot: float, keep: float, exclude) -> list[tuple[float, float, float]]:
    """Buildings on a lot grid; returns their footprint discs."""
    yaw0 = rng.uniform(0, np.pi / 2)
    rot = _rot_z(yaw0)[:2, :2]
    discs = []
    for i in range(nx):
        for j in range(ny):
            if rng.random() > keep:
                continue
            off = rot @ np.array([(i - (nx - 1) / 2) * lot, (j - (ny - 1) / 2) * lot])
            x, y = cx + off[0], cy + off[1]
            length = rng.uniform(0.35, 0.7) * lot
            width = rng.uniform(0.3, 0.55) * lot
            if exclude(np.array([[x, y]]), math.hypot(length, width) / 2 + 4)[0]:
                continue
            roof = rng.choice(["flat", "gable", "gable", "hip"])
            wall = rng.uniform(3.0, 8.0)
            b.add_building(x, y, yaw0 + rng.normal(0, 0.05) + rng.choice([0, np.pi / 2]),
                           length, width, wall, roof, rng.uniform(0.25, 0.45) * width,
                           rng.uniform(0.42, 0.62))
            discs.append((x, y, math.hypot(length, width) / 2 + 1.5))
    return discs


def _build_mixed(rng: np.random.Generator) -> tuple[_Builder, _Path]:
    terrain = _make_terrain(rng, slope_max=0.03, n_hills=9, amp=(6, 22), sigma=(70, 150),
                            detail=0.35)
    b = _Builder(terrain)
    # Power line A runs north-south past the start of the flight; line B ends in the west.
    ya = 15.0 + 250.0 * np.arange(-2, 3)
    line_a = np.column_stack([10.0 + rng.uniform(-12, 12, 5) * (ya != 15.0), ya])
    xb = np.linspace(-560.0, -70.0, 4)
    line_b = np.column_stack([xb, -330.0 + rng.uniform(-15, 15, 4)])
    b.add_power_line(line_a, rng.uniform(33, 37, len(line_a)))
    b.add_power_line(line_b, rng.uniform(30, 34, len(line_b)))
    road_y = -28.0

    def exclude(pts: np.ndarray, r: float) -> np.ndarray:
        return (_near_polyline(pts, line_a, 22 + r) | _near_polyline(pts, line_b, 22 + r)
                | (np.abs(pts[:, 1] - road_y) < 6 + r))

    discs = _add_village(b, rng, -110.0, 12.0, 4, 3, 26.0, 0.9, exclude)
    for _ in range(3):
        c = rng.uniform(-450, 450, 2)
        discs += _add_village(b, rng, c[0], c[1], int(rng.integers(3, 6)),
                              int(rng.integers(2, 5)), 24.0, 0.7, exclude)
    discs_a = np.array(discs).reshape(-1, 3)
    # Woods: a patch east of the start and random patches; hedgerows; scattered trees.
    patches = np.vstack([[75.0, 20.0, 45.0],
                         np.column_stack([rng.uniform(-500, 500, (8, 2)),
                                          rng.uniform(40, 110, 8)])])
    pts = _jittered(rng, 6.0, 0.85)
    wood = pts[_in_discs(pts, patches)]
    scattered = rng.uniform(-_CONTENT_HALF, _CONTENT_HALF, (400, 2))
    hedges = []
    for _ in range(6):
        a = rng.uniform(-500, 500, 2)
        ang = rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.1)
        s = np.arange(0, rng.uniform(150, 400), 7.0)
        hedges.append(a + np.outer(s, [math.cos(ang), math.sin(ang)])
                      + rng.normal(0, 1, (len(s), 2)))
    trees = np.vstack([wood, scattered] + hedges)
    ok = ~(exclude(trees, 3.0) | _in_discs(trees, discs_a + [0, 0, 3]))
    trees = trees[ok]
    b.add_trees(trees[:, 0], trees[:, 1], _tree_heights(rng, len(trees), 4.0, 24.0), rng)
    shrubs = _jittered(rng, 9.0, 0.5)
    shrubs = shrubs[_in_discs(shrubs, patches) | (rng.random(len(shrubs)) < 0.08)]
    shrubs = shrubs[~(_in_discs(shrubs, discs_a) | (np.abs(shrubs[:, 1] - road_y) < 5))]
    b.add_shrubs(shrubs[:, 0], shrubs[:, 1], _shrub_heights(rng, len(shrubs)), rng)
    # Meadows: low cover (class 3), one by the start of the flight.
    meadows = np.vstack([[-45.0, -8.0, 22.0],
                         np.column_stack([rng.uniform(-500, 500, (6, 2)),
                                          rng.uniform(30, 70, 6)])])
    low = _jittered(rng, 3.0, 0.7)
    low = low[_in_discs(low, meadows) & ~exclude(low, 1.0) & ~_in_discs(low, discs_a)]
    b.add_shrubs(low[:, 0], low[:, 1], rng.uniform(0.2, 0.5, len(low)), rng)
    # Street lights along the road, away from the towers.
    px = np.arange(-520.0, 520.0, 35.0) + 5.0
    poles = np.column_stack([px, np.full(len(px), road_y - 6.0)])
    poles = poles[~_near_polyline(poles, line_a, 12) & ~_near_polyline(poles, line_b, 12)]
    b.add_poles(poles[:, 0], poles[:, 1], rng.uniform(8.0, 11.0, len(poles)))
    path = _Path(_lawnmower(-430.0, 430.0, -400.0, 50.0, 18), 22.0, (-100.0, 0.0))
    return b, path


def _build_corridor(rng: np.random.Generator) -> tuple[_Builder, _Path]:
    terrain = _make_terrain(rng, slope_max=0.02, n_hills=5, amp=(3, 10), sigma=(80, 160),
                            detail=0.3)
    b = _Builder(terrain)
    xs = np.linspace(-590.0, 590.0, 6)
    line = np.column_stack([xs, rng.uniform(-8, 8, len(xs))])
    b.add_power_line(line, rng.uniform(33, 37, len(line)))

    def exclude(pts: np.ndarray, r: float) -> np.ndarray:
        return _near_polyline(pts, line, 20 + r)

    discs = _add_village(b, rng, 150.0, -110.0, 2, 2, 28.0, 1.0, exclude)
    discs_a = np.array(discs).reshape(-1, 3)
    patches = np.column_stack([rng.uniform(-500, 500, (6, 2)), rng.uniform(40, 90, 6)])
    patches[:, 1] = np.where(np.abs(patches[:, 1]) < 60, patches[:, 1] + 120, patches[:, 1])
    pts = _jittered(rng, 6.5, 0.8)
    trees = np.vstack([pts[_in_discs(pts, patches)],
                       rng.uniform(-_CONTENT_HALF, _CONTENT_HALF, (300, 2))]
                      + [np.column_stack([np.arange(-520.0, 520.0, 8.0),
                                          np.full(130, yh) + rng.normal(0, 1, 130)])
                         for yh in (-45.0, 52.0)])
    trees = trees[~(exclude(trees, 3.0) | _in_discs(trees, discs_a + [0, 0, 3]))]
    b.add_trees(trees[:, 0], trees[:, 1], _tree_heights(rng, len(trees), 4.0, 22.0), rng)
    # Fields: low crops and bushes, also under the line (the corridor is kept low).
    shrubs = _jittered(rng, 7.0, 0.35)
    shrubs = shrubs[~_in_discs(shrubs, discs_a)]
    b.add_shrubs(shrubs[:, 0], shrubs[:, 1], _shrub_heights(rng, len(shrubs)), rng)
    px = np.arange(-500.0, 500.0, 40.0)
    poles = np.column_stack([px, np.full(len(px), -80.0)])
    b.add_poles(poles[:, 0], poles[:, 1], rng.uniform(8.0, 10.0, len(poles)))
    corners = np.array([[-480.0, -16.0], [480.0, -16.0], [480.0, 16.0], [-480.0, 16.0]])
    path = _Path(corners, 15.5, (-135.0, -16.0))   # a tower is in view at once
    return b, path


def _build_urban(rng: np.random.Generator) -> tuple[_Builder, _Path]:
    terrain = _make_terrain(rng, slope_max=0.01, n_hills=3, amp=(1, 4), sigma=(120, 200),
                            detail=0.08)
    b = _Builder(terrain)
    block, street = 70.0, 14.0
    centres = np.arange(-_CONTENT_HALF + block / 2, _CONTENT_HALF, block)
    discs = []
    parks = []
    for cx in centres:
        for cy in centres:
            if rng.random() < 0.12:
                parks.append((cx, cy, (block - street) / 2))
                continue
            sub = (block - street) / 2
            for i in (-0.5, 0.5):
                for j in (-0.5, 0.5):
                    if rng.random() < 0.15:
                        continue
                    x, y = cx + i * sub, cy + j * sub
                    tall = rng.random() < 0.3
                    length = rng.uniform(0.55, 0.85) * sub
                    width = rng.uniform(0.45, 0.8) * sub
                    # Up to 20 m: the UAV flies 40 m above the ground.
                    wall = rng.uniform(10.0, 20.0) if tall else rng.uniform(3.0, 9.0)
                    roof = "flat" if tall else rng.choice(["flat", "gable", "hip"])
                    b.add_building(x, y, rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.02),
                                   length, width, wall, roof, rng.uniform(0.25, 0.4) * width,
                                   rng.uniform(0.42, 0.65))
                    discs.append((x, y, math.hypot(length, width) / 2 + 1.0))
    discs_a = np.array(discs).reshape(-1, 3)
    parks_a = np.array(parks).reshape(-1, 3) * [1, 1, 1.3]
    # Street trees and lights along both sides of every street.
    edges = centres[:-1] + block / 2
    along = np.arange(-_CONTENT_HALF, _CONTENT_HALF, 12.0)
    side = []
    for e in edges:
        for off in (-street / 2 + 1.0, street / 2 - 1.0):
            side.append(np.column_stack([along, np.full(len(along), e + off)]))
            side.append(np.column_stack([np.full(len(along), e + off), along]))
    side_a = np.vstack(side)
    lights = side_a[(np.round(side_a.sum(axis=1) / 12.0) % 3) == 0]
    street_trees = side_a[rng.random(len(side_a)) < 0.3]
    light_discs = np.column_stack([lights, np.full(len(lights), 3.0)])
    street_trees = street_trees[~_in_discs(street_trees, light_discs)]
    park_pts = _jittered(rng, 7.0, 0.8)
    trees = np.vstack([street_trees, park_pts[_in_discs(park_pts, parks_a)]])
    trees = trees[~_in_discs(trees, discs_a + [0, 0, 2])]
    b.add_trees(trees[:, 0], trees[:, 1], _tree_heights(rng, len(trees), 4.0, 16.0), rng)
    shrubs = _jittered(rng, 8.0, 0.5)
    shrubs = shrubs[_in_discs(shrubs, parks_a) & ~_in_discs(shrubs, discs_a)]
    b.add_shrubs(shrubs[:, 0], shrubs[:, 1], _shrub_heights(rng, len(shrubs)), rng)
    b.add_poles(lights[:, 0], lights[:, 1], rng.uniform(7.0, 9.0, len(lights)))
    path = _Path(_lawnmower(-430.0, 430.0, -400.0, 50.0, 18), 22.0, (-100.0, 0.0))
    return b, path


def _build_forest(rng: np.random.Generator) -> tuple[_Builder, _Path]:
    terrain = _make_terrain(rng, slope_max=0.04, n_hills=12, amp=(8, 28), sigma=(60, 140),
                            detail=0.5)
    b = _Builder(terrain)
    clearings = np.column_stack([rng.uniform(-500, 500, (10, 2)), rng.uniform(20, 60, 10)])
    discs = np.array(_add_village(b, rng, -20.0, 10.0, 2, 1, 30.0, 1.0,
                                  lambda p, r: np.zeros(len(p), bool))).reshape(-1, 3)
    clearings = np.vstack([clearings, [-20.0, 10.0, 35.0]])
    trees = _jittered(rng, 6.5, 0.85)
    trees = trees[~_in_discs(trees, clearings)]
    b.add_trees(trees[:, 0], trees[:, 1], _tree_heights(rng, len(trees), 5.0, 28.0), rng)
    shrubs = _jittered(rng, 7.0, 0.45)
    shrubs = shrubs[~_in_discs(shrubs, discs)]
    b.add_shrubs(shrubs[:, 0], shrubs[:, 1], _shrub_heights(rng, len(shrubs)), rng)
    path = _Path(_lawnmower(-430.0, 430.0, -400.0, 50.0, 18), 22.0, (-100.0, 0.0))
    return b, path


_BUILDERS = {"mixed": _build_mixed, "corridor": _build_corridor, "urban": _build_urban,
             "forest": _build_forest}


@functools.lru_cache(maxsize=4)
def _scene(name: str, seed: int) -> _Scene:
    rng = np.random.default_rng([int(seed), SCENES.index(name), 0x5CE7E])
    builder, path = _BUILDERS[name](rng)
    return builder.finish(name, int(seed), path)


def _resolve(scene_or_settings: "str | SimSettings") -> _Scene:
    if isinstance(scene_or_settings, SimSettings):
        return _scene(scene_or_settings.scene, int(scene_or_settings.seed))
    if isinstance(scene_or_settings, str):
        return _scene(SimSettings(scene=scene_or_settings).scene, 0)
    raise ConfigError(f"scene: expected a scene name or SimSettings, got "
                      f"{type(scene_or_settings).__name__}")


def scene_ground_height(scene_or_settings: "str | SimSettings", xy: np.ndarray) -> np.ndarray:
    """True terrain height under ``xy``.

    ``scene_or_settings``: a scene name (seed 0) or :class:`SimSettings` (its scene and
    seed). ``xy``: (N, 2) float, map frame, metres. Returns (N,) float64 metres. The
    terrain is defined on [-640, 640]^2 m and extended flat-wise outside.
    """
    scene = _resolve(scene_or_settings)
    xy = points_xyz(xy, "scene_ground_height: xy", columns=2, nonfinite="keep")
    return scene.terrain.height(xy[:, 0], xy[:, 1])


def scene_info(scene_or_settings: "str | SimSettings") -> SceneInfo:
    """What the scene of ``scene_or_settings`` (name with seed 0, or settings) contains."""
    s = _resolve(scene_or_settings)
    return SceneInfo(name=s.name, seed=s.seed,
                     extent=(-_CONTENT_HALF, _CONTENT_HALF, -_CONTENT_HALF, _CONTENT_HALF),
                     towers=s.towers.copy(), tower_heights=s.tower_heights.copy(),
                     spans=s.spans.copy(), n_trees=s.n_trees, n_shrubs=s.n_shrubs,
                     n_buildings=s.n_buildings, n_poles=s.n_poles, path_length=s.path.length)


# --------------------------------------------------------------------------- flight


def _quaternion(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(4,) x y z w of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def _rotation(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _pose(scene: _Scene, settings: SimSettings, t: float, phase: np.ndarray):
    """Position (3,), quaternion (4,), rotation (3, 3) and velocity (3,) at time t, s."""
    h = 0.05
    times = np.array([t - h, t, t + h])
    xy, head = scene.path.xy(settings.speed * times)
    z = scene.terrain.smooth(xy[:, 0], xy[:, 1]) + settings.altitude
    pos = np.column_stack([xy, z])
    vel = (pos[2] - pos[0]) / (2 * h)
    yaw = math.atan2(head[1, 1], head[1, 0])
    # Multirotor attitude: nose down in forward flight plus a slow wobble.
    pitch = math.radians(0.4 * settings.speed + 1.5 * math.sin(0.9 * t + phase[0]))
    roll = math.radians(2.0 * math.sin(0.6 * t + phase[1]))
    q = _quaternion(roll, pitch, yaw)
    return pos[1], q, _rotation(q), vel


def simulate_flight(settings: SimSettings) -> Iterator[SimFrame]:
    """The clouds of a labelled synthetic flight, one per ``1 / settings.rate`` s.

    Returns an iterator of :class:`SimFrame` (``ceil(duration * rate)`` frames, frame k
    stamped k / rate). Lazy: each frame is made when asked for, memory stays flat
    whatever the duration. Deterministic: the same settings give the same bytes.
    Raises :class:`ConfigError` at once when ``settings`` is not a :class:`SimSettings`.
    """
    if not isinstance(settings, SimSettings):
        raise ConfigError(f"settings: expected SimSettings, got {type(settings).__name__}")
    # Checked (and the scene built) now, not at the first next().
    return _frames(_scene(settings.scene, int(settings.seed)), settings)


def _frames(scene: _Scene, settings: SimSettings) -> Iterator[SimFrame]:
    n_frames = max(1, math.ceil(settings.duration * settings.rate - 1e-9))
    phase = np.random.default_rng([int(settings.seed), 7]).uniform(0, 2 * np.pi, 2)
    echoes_per_pulse = 1.15
    next_id = 0
    for k in range(n_frames):
        rng = np.random.default_rng([int(settings.seed), 1, k])
        stamp = k / settings.rate
        pos, quat, rot, vel = _pose(scene, settings, stamp, phase)
        pulses = max(16, int(round(settings.points_per_frame / echoes_per_pulse)))
        pts, fired = _scan(scene, settings, rng, pos, rot, vel, pulses)
        n = len(pts["xyz"])
        # The pulse count adapts so that the echo count stays near the target.
        echoes_per_pulse = 0.6 * echoes_per_pulse + 0.4 * max(n / fired, 0.5)
        out = np.empty(n, dtype=POINT_DTYPE)
        xyz = pts["xyz"]
        if settings.frame == "sensor":
            xyz = (xyz - pos) @ rot
        out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        out["intensity"] = pts["intensity"]
        out["return_number"] = pts["return_number"]
        out["number_of_returns"] = pts["number_of_returns"]
        out["classification"] = pts["classification"]
        out["point_id"] = np.arange(next_id, next_id + n, dtype=np.uint64).astype(np.uint32)
        next_id += n
        if next_id >= 2**32:
            raise ConfigError(f"duration: {settings.duration:g} s overflows the uint32 "
                              f"point_id after {k + 1} frames")
        yield SimFrame(stamp=stamp, points=out, position=pos, orientation=quat,
                       velocity=vel)


# --------------------------------------------------------------------------- ray casting


def _directions(settings: SimSettings, rng: np.random.Generator, pulses: int) -> np.ndarray:
    """(P, 3) unit pulse directions in the sensor frame (x forward, y left, z up).

    A jittered grid in the tangent plane z = -1: uniform density on flat ground, one
    across-track sweep per row, rows in time order (like a 2-D scanning LiDAR).
    """
    ua = math.tan(math.radians(settings.fov_across / 2))
    va = math.tan(math.radians(settings.fov_along / 2))
    ny = max(1, int(math.ceil(math.sqrt(pulses * ua / va))))
    nx = max(1, int(math.ceil(pulses / ny)))
    j = np.arange(ny * nx)
    row, col = j // ny, j % ny
    col = np.where(row % 2 == 1, ny - 1 - col, col)
    u = -ua + 2 * ua * (col + rng.random(len(j))) / ny
    v = va - 2 * va * (row + rng.random(len(j))) / nx
    d = np.column_stack([v, u, -np.ones(len(j))])
    return d / np.sqrt(1.0 + u * u + v * v)[:, None]


def _ground_hits(terrain: _Terrain, o: np.ndarray, d: np.ndarray):
    """Range t (P,) to the terrain along each ray, and the terrain gradient there.

    Newton on g(t) = o_z + t d_z - f(o_xy + t d_xy) from the flat-ground guess; the
    residual is below 1e-8 m after three steps on every scene (slopes < 0.4, rays
    within 60 deg of nadir); the gradient of the last step is kept (for the incidence).
    """
    z0 = terrain.height(o[:, 0], o[:, 1])
    t = (o[:, 2] - z0) / -d[:, 2]
    for _ in range(3):
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
        z, gx, gy = terrain.height_grad(x, y)
        g = o[:, 2] + t * d[:, 2] - z
        dg = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
        t = t - g / np.minimum(dg, -0.05)
    return t, gx, gy


def _pairs(scene: _Scene, prims: np.ndarray, centre: np.ndarray, u: np.ndarray,
           v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ray, primitive) pairs whose ray may meet the primitive's bounding box.

    Boxes are projected from ``centre`` into the tangent plane z = -1 (below the sensor)
    where the rays sit at (u, v); rays are bucketed in u-strips sorted by v.
    """
    box = scene.box[prims]
    lo = box[:, 0] - _CULL_MARGIN - centre
    hi = box[:, 1] + _CULL_MARGIN - centre
    top = np.minimum(hi[:, 2], -0.5)     # rays go down: only the part below the sensor
    keep = lo[:, 2] < top
    prims, lo, hi, top = prims[keep], lo[keep], hi[keep], top[keep]
    if len(prims) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cx = np.stack([lo[:, 0], hi[:, 0]], axis=1)[:, :, None]
    cy = np.stack([lo[:, 1], hi[:, 1]], axis=1)[:, :, None]
    inv = 1.0 / -np.stack([lo[:, 2], top], axis=1)[:, None, :]
    pu = (cx * inv).reshape(len(prims), -1)
    pv = (cy * inv).reshape(len(prims), -1)
    u0, u1 = pu.min(axis=1), pu.max(axis=1)
    v0, v1 = pv.min(axis=1), pv.max(axis=1)
    umin, umax = float(u.min()), float(u.max())
    vmin, vmax = float(v.min()), float(v.max())
    keep = (u1 >= umin) & (u0 <= umax) & (v1 >= vmin) & (v0 <= vmax)
    prims, u0, u1, v0, v1 = prims[keep], u0[keep], u1[keep], v0[keep], v1[keep]
    n_strips = 64
    width = (umax - umin) / n_strips + 1e-12
    strip = np.minimum(((u - umin) / width).astype(np.int64), n_strips - 1)
    span = vmax - vmin + 1.0
    key = strip * span + (v - vmin)
    order = np.argsort(key)
    key = key[order]
    s0 = np.clip(((u0 - umin) / width).astype(np.int64), 0, n_strips - 1)
    s1 = np.clip(((u1 - umin) / width).astype(np.int64), 0, n_strips - 1)
    ns = s1 - s0 + 1
    p_idx = np.repeat(np.arange(len(prims)), ns)
    st = s0[p_idx] + np.arange(ns.sum()) - np.repeat(np.cumsum(ns) - ns, ns)
    a = np.searchsorted(key, st * span + (np.clip(v0[p_idx], vmin, vmax) - vmin), "left")
    b = np.searchsorted(key, st * span + (np.clip(v1[p_idx], vmin, vmax) - vmin), "right")
    cnt = b - a
    total = int(cnt.sum())
    ray = order[np.repeat(a, cnt) + np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)]
    prim_local = np.repeat(p_idx, cnt)
    ok = (u[ray] >= u0[prim_local]) & (u[ray] <= u1[prim_local])
    return ray[ok], prims[prim_local[ok]]


def _hit_polys(scene: _Scene, ray, idx, o, d):
    """Entry range into convex buildings; returns mask, t, reflectance, cos incidence."""
    pl = scene.planes[idx]                                # (K, 9, 4)
    denom = np.einsum("kpj,kj->kp", pl[:, :, :3], d[ray])
    num = pl[:, :, 3] - np.einsum("kpj,kj->kp", pl[:, :, :3], o[ray])
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = num / denom
    entering = denom < -1e-12
    leaving = denom > 1e-12
    t_in = np.where(entering, tt, -np.inf)
    face = np.argmax(t_in, axis=1)
    t0 = t_in[np.arange(len(ray)), face]
    t1 = np.where(leaving, tt, np.inf).min(axis=1)
    parallel_out = (~entering & ~leaving & (num < 0)).any(axis=1)
    hit = (t0 <= t1) & (t0 > 0) & ~parallel_out
    refl = scene.plane_refl[idx, face]
    cos = -denom[np.arange(len(ray)), face]
    return hit, t0, refl, cos


def _hit_cylinders(scene: _Scene, ray, idx, o, d):
    """Vertical cylinders (trunks, poles): side or top cap. mask, t, cos incidence."""
    c = scene.cyl[idx]
    ox = o[ray, 0] - c[:, 0]
    oy = o[ray, 1] - c[:, 1]
    dx, dy, dz = d[ray, 0], d[ray, 1], d[ray, 2]
    a = dx * dx + dy * dy
    bb = ox * dx + oy * dy
    cc = ox * ox + oy * oy - c[:, 4] ** 2
    disc = bb * bb - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-bb - np.sqrt(disc)) / a
    z_side = o[ray, 2] + t_side * dz
    side = (disc > 0) & (t_side > 0) & (z_side >= c[:, 2]) & (z_side <= c[:, 3])
    t_cap = (c[:, 3] - o[ray, 2]) / dz
    rx = ox + t_cap * dx
    ry = oy + t_cap * dy
    cap = (t_cap > 0) & (rx * rx + ry * ry <= c[:, 4] ** 2)
    t = np.where(cap, t_cap, t_side)
    with np.errstate(invalid="ignore"):
        nx, ny = (ox + t * dx) / c[:, 4], (oy + t * dy) / c[:, 4]
    cos = np.where(cap, -dz, np.abs(nx * dx + ny * dy))
    return side | cap, t, cos


def _hit_segments(scene: _Scene, ray, idx, o, d, wire_radius: float):
    """Thin cylinders (tower members, wire pieces): mask, t of closest approach."""
    s = scene.seg[idx]
    p0 = s[:, 0:3]
    e = s[:, 3:6] - p0
    r = np.where(s[:, 7] == WIRE, wire_radius, s[:, 6])
    w0 = o[ray] - p0
    dd = d[ray]
    b = np.einsum("ij,ij->i", dd, e)
    c = np.einsum("ij,ij->i", e, e)
    dw = np.einsum("ij,ij->i", dd, w0)
    ew = np.einsum("ij,ij->i", e, w0)
    denom = c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        sp = np.where(denom > 1e-9, (ew - b * dw) / denom, 0.0)
    sp = np.clip(sp, 0.0, 1.0)
    t = sp * b - dw
    gap = w0 + t[:, None] * dd - sp[:, None] * e
    dist2 = np.einsum("ij,ij->i", gap, gap)
    hit = (dist2 < r * r) & (t > 0)
    return hit, t - np.sqrt(np.maximum(r * r - dist2, 0.0))


def _hit_ellipsoids(scene: _Scene, ray, idx, o, d):
    """Ray intervals [t_in, t_out] inside crowns / shrubs, and their extinction, 1/m."""
    # Component-wise on contiguous columns: the hot loop of wooded scenes (10^5 pairs).
    cx, cy, cz, ix, iy, iz, lam = (c[idx] for c in scene.ell_cols)
    ox = (o[:, 0][ray] - cx) * ix
    oy = (o[:, 1][ray] - cy) * iy
    oz = (o[:, 2][ray] - cz) * iz
    dx = d[:, 0][ray] * ix
    dy = d[:, 1][ray] * iy
    dz = d[:, 2][ray] * iz
    a = dx * dx + dy * dy + dz * dz
    b = ox * dx + oy * dy + oz * dz
    disc = b * b - a * (ox * ox + oy * oy + oz * oz - 1.0)
    hit = disc > 0
    root = np.sqrt(np.where(hit, disc, 0.0))
    t1 = (root - b) / a
    hit &= t1 > 0
    return hit, np.maximum((-b - root) / a, 0.0), t1, lam


def _scan(scene: _Scene, settings: SimSettings, rng: np.random.Generator, pos: np.ndarray,
          rot: np.ndarray, vel: np.ndarray,
          pulses: int) -> tuple[dict[str, np.ndarray], int]:
    """Ray-cast one frame: map-frame echoes with their labels in pulse order, pulses fired."""
    # Column-major so that per-axis columns are contiguous.
    d = np.asfortranarray(_directions(settings, rng, pulses) @ rot.T)
    n = len(d)
    dt = 1.0 / settings.rate
    tau = (np.arange(n) + 0.5) / n * dt - dt / 2     # pulse times around the stamp
    o = np.asfortranarray(pos + tau[:, None] * vel)
    t_g, gx, gy = _ground_hits(scene.terrain, o, d)
    gxs = o[:, 0] + t_g * d[:, 0]
    gys = o[:, 1] + t_g * d[:, 1]

    # Candidates: solid hits end the pulse, partial echoes let it go on.
    c_ray, c_t, c_cls, c_refl, c_cos, c_cont = [], [], [], [], [], []

    def add(ray, t, cls, refl, cos, cont):
        c_ray.append(ray)
        c_t.append(t)
        c_cls.append(np.broadcast_to(np.asarray(cls, np.uint8), ray.shape))
        c_refl.append(np.broadcast_to(np.asarray(refl, np.float64), ray.shape))
        c_cos.append(np.broadcast_to(np.asarray(cos, np.float64), ray.shape))
        c_cont.append(np.broadcast_to(np.asarray(cont, np.float64), ray.shape))

    rays = np.arange(n)
    cos_g = (-d[:, 2] + gx * d[:, 0] + gy * d[:, 1]) / np.sqrt(1 + gx * gx + gy * gy)
    add(rays, t_g, GROUND, scene.terrain.ground_reflectance(gxs, gys), cos_g, 0.0)

    # Everything a pulse can meet lies between its origin and its ground hit.
    prims = scene.grid.query(min(gxs.min(), o[0, 0], o[-1, 0]),
                             max(gxs.max(), o[0, 0], o[-1, 0]),
                             min(gys.min(), o[0, 1], o[-1, 1]),
                             max(gys.max(), o[0, 1], o[-1, 1]))
    u = d[:, 0] / -d[:, 2]
    v = d[:, 1] / -d[:, 2]
    ray, prim = _pairs(scene, prims, pos, u, v)
    kind = scene.kind[prim]
    index = scene.index[prim]

    m = kind == _POLY
    if m.any():
        hit, t, refl, cos = _hit_polys(scene, ray[m], index[m], o, d)
        add(ray[m][hit], t[hit], BUILDING, refl[hit], cos[hit], 0.0)
    m = kind == _CYL
    if m.any():
        hit, t, cos = _hit_cylinders(scene, ray[m], index[m], o, d)
        c = scene.cyl[index[m][hit]]
        add(ray[m][hit], t[hit], c[:, 5], c[:, 6], cos[hit], 0.0)

    # Nearest solid hit per pulse (every pulse has one: the ground, the first entry).
    t_solid = t_g.copy()
    if len(c_ray) > 1:
        np.minimum.at(t_solid, np.concatenate(c_ray[1:]), np.concatenate(c_t[1:]))

    m = kind == _SEG
    if m.any():
        hit, t = _hit_segments(scene, ray[m], index[m], o, d, settings.wire_radius)
        r, t, i = ray[m][hit], t[hit], index[m][hit]
        ok = t < t_solid[r] - _PULSE_SEPARATION
        r, t, i = r[ok], t[ok], i[ok]
        cls = scene.seg[i, 7].astype(np.uint8)
        cont = np.where(cls == WIRE, _ECHO_CONTINUE["wire"], _ECHO_CONTINUE["tower"])
        add(r, t, cls, scene.seg[i, 8], rng.uniform(0.5, 1.0, len(r)), cont)
    m = kind == _ELL
    if m.any():
        hit, t0, t1, lam = _hit_ellipsoids(scene, ray[m], index[m], o, d)
        r, t0, t1, lam = ray[m][hit], t0[hit], t1[hit], lam[hit]
        ts = t_solid[r]
        t1 = np.minimum(t1, ts)
        # Free path inside the foliage is exponential; up to three echoes per crown. An
        # echo closer to the surface behind it than the pulse separation merges with it:
        # low cover hides the ground there (the pulse stops).
        t = t0 + rng.standard_exponential(len(r), dtype=np.float32) / lam
        for step in range(3):
            ok = np.flatnonzero(t < t1)
            cont = np.where(t[ok] > ts[ok] - _PULSE_SEPARATION, 0.0, _ECHO_CONTINUE["veg"])
            add(r[ok], t[ok], _VEGETATION, _R_VEG, rng.uniform(0.3, 1.0, len(ok)), cont)
            if step < 2:
                t = t + _PULSE_SEPARATION + rng.standard_exponential(
                    len(r), dtype=np.float32) / lam

    all_ray = np.concatenate(c_ray)
    all_t = np.concatenate(c_t)
    keep = all_t <= t_solid[all_ray]     # drop solid hits behind the nearest one
    all_ray, all_t = all_ray[keep], all_t[keep]
    cls = np.concatenate(c_cls)[keep]
    refl = np.concatenate(c_refl)[keep]
    cos = np.concatenate(c_cos)[keep]
    cont = np.concatenate(c_cont)[keep]

    # Outliers: a few pulses give only one echo, far above or below the surface.
    n_out = int(rng.binomial(n, settings.outlier_rate))
    out_rays = np.unique(rng.integers(0, n, n_out))
    if len(out_rays):
        keep = ~np.isin(all_ray, out_rays)
        all_ray, all_t, cls, refl, cos, cont = (a[keep] for a in
                                                (all_ray, all_t, cls, refl, cos, cont))
        ts = t_solid[out_rays]
        above = rng.random(len(out_rays)) < 0.5
        # Above: at least 5.6 m before the first surface; below: 4-20 m under the terrain.
        t_out = np.where(above, rng.uniform(0.15, 0.7, len(out_rays)) * np.maximum(ts - 8, 2),
                         t_g[out_rays] + rng.uniform(4.0, 20.0, len(out_rays)))
        all_ray = np.concatenate([all_ray, out_rays])
        all_t = np.concatenate([all_t, t_out])
        cls = np.concatenate([cls, np.full(len(out_rays), NOISE, np.uint8)])
        refl = np.concatenate([refl, rng.uniform(0.01, 0.1, len(out_rays))])
        cos = np.concatenate([cos, np.ones(len(out_rays))])
        cont = np.concatenate([cont, np.zeros(len(out_rays))])

    # One float key sorts by pulse, then range (ranges stay far below 4096 m).
    order = np.argsort(all_ray * 4096.0 + np.clip(all_t, 0.0, 4095.0))
    ray_s = all_ray[order]
    m = len(ray_s)
    idx = np.arange(m)
    first = np.r_[True, ray_s[1:] != ray_s[:-1]]
    first_idx = np.maximum.accumulate(np.where(first, idx, 0))
    rank = idx - first_idx
    # A pulse goes on past a partial echo with probability `cont`; count the stops.
    stop = (rng.random(m, dtype=np.float32) >= cont[order]).astype(np.int64)
    stops_before = np.cumsum(stop) - stop
    alive = (stops_before == stops_before[first_idx]) & (rank < settings.max_returns)
    sel = np.flatnonzero(alive)
    take = order[sel]     # one gather per array, straight from the unsorted candidates
    all_ray, all_t, cls, refl, cos = (a[take] for a in (all_ray, all_t, cls, refl, cos))
    rank = rank[sel]
    n_ret = np.bincount(all_ray, minlength=n)[all_ray]

    all_t = all_t + settings.range_noise * rng.standard_normal(len(all_t), dtype=np.float32)
    xyz = np.empty((len(all_t), 3))
    for axis in range(3):    # per column: o and d are column-major
        xyz[:, axis] = o[:, axis][all_ray] + all_t * d[:, axis][all_ray]
    veg = np.flatnonzero(cls == _VEGETATION)
    if len(veg):
        hag = xyz[veg, 2] - scene.terrain.height(xyz[veg, 0], xyz[veg, 1])
        cls[veg] = np.where(hag < 0.5, LOW_VEG, np.where(hag < 2.0, MEDIUM_VEG, HIGH_VEG))
    # Intensity: reflectance x incidence, energy shared by the echoes of a pulse.
    energy = np.where(n_ret > 1, 0.8 * 0.85 ** rank, 1.0)
    inten = refl * (0.35 + 0.65 * np.clip(cos, 0.0, 1.0)) * energy
    inten = inten + 0.015 * rng.standard_normal(len(inten), dtype=np.float32)
    inten = np.clip(inten, 0.002, 1.0)
    return {"xyz": xyz, "intensity": (inten * INTENSITY_SCALE).astype(np.float32),
            "return_number": (rank + 1).astype(np.uint8),
            "number_of_returns": n_ret.astype(np.uint8), "classification": cls}, n
