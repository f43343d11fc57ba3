"""Gaussian-map feature points (core.features, seed 001): accuracy on shapes with known
edges, speed and feature share on real data, faithful against fast, with an anchor.

(a) Synthetic shapes with known feature lines, sampled at random (Poisson, 16 pts/m^2 on
    surfaces: 0.25 m spacing, like an airborne scan) with Gaussian noise per coordinate:
    a box (5 faces, no floor), gable houses of 20 and 45 deg pitch (walls + roof), a
    lattice tower (legs and X braces as 0.1 m members), a sagging wire, and the box and
    the 20 deg house with two tree crowns beside them (crown points are never near an
    edge: what an obstacle cloud beside trees looks like). Precision: the
    share of feature points within 2.5 spacings (the reach of 14 neighbours) of a true
    edge; recall: the share of points within 1 spacing of one that are found. Tower and
    wire points all lie on their lines (only recall says something there). Methods:
    `faithful`, `fast` and the anchor, the classic PCA surface variation l3 / sum(l) of
    the same 14 neighbours thresholded at the share of feature points `fast` found on
    the same shape. `agree`: share of points where fast and faithful decide alike.
(b) Real data: AHN4 building points (class 6) and a corridor crop (a 40 m disc around a
    tower: towers, wires, trees, cranes; no ground or water): feature share, seconds,
    ms per 10 000 points; the paper's sculpture in kind: 48 238 -> 6 855 points
    (14.21 %) in 10 s (2 070 ms per 10 000 points).

Usage: .venv/bin/python benchmarks/bench_features.py [--quick | --smoke --out DIR]
Writes benchmarks/results/features.json (to --out DIR if given) and prints Markdown tables.
"""
from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidar_obstacles.config import FeaturesConfig  # noqa: E402
from lidar_obstacles.core.features import gaussian_map_features  # noqa: E402
from lidar_obstacles.io.las import read_las  # noqa: E402
from common import bench_args, per_mode  # noqa: E402 (benchmarks/ is on the path)

DATA = REPO.parent / "shared" / "data"
DENSITY = 16.0  # points / m^2 on surfaces
SPACING = 1.0 / np.sqrt(DENSITY)  # m
PRECISION_BAND = 2.5 * SPACING  # m
RECALL_BAND = 1.0 * SPACING  # m
PAPER = {"points": 48238, "feature_points": 6855, "share": 0.1421, "seconds": 10.0}

# --------------------------------------------------------------------------- shapes


def _sample_triangles(tris: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    tris = np.asarray(tris, float)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]),
                                axis=1)
    which = np.repeat(np.arange(len(tris)), rng.poisson(area * DENSITY))
    u, v = rng.random((2, len(which)))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tris[which]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def _quad(a, b, c, d) -> list:
    return [[a, b, c], [a, c, d]]


def box(rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """10 x 8 x 6 m box without floor: 4 roof edges and 4 wall corners are creases (the
    wall feet are open borders, not creases)."""
    L, W, H = 10.0, 8.0, 6.0
    c = np.array([(0, 0, 0), (L, 0, 0), (L, W, 0), (0, W, 0),
                  (0, 0, H), (L, 0, H), (L, W, H), (0, W, H)], float)
    tris = (_quad(c[4], c[5], c[6], c[7]) + _quad(c[0], c[1], c[5], c[4])
            + _quad(c[1], c[2], c[6], c[5]) + _quad(c[2], c[3], c[7], c[6])
            + _quad(c[3], c[0], c[4], c[7]))
    edges = [(c[4], c[5]), (c[5], c[6]), (c[6], c[7]), (c[7], c[4]),
             (c[0], c[4]), (c[1], c[5]), (c[2], c[6]), (c[3], c[7])]
    return _sample_triangles(np.array(tris), rng), edges


def gable(rng: np.random.Generator, pitch_deg: float) -> tuple[np.ndarray, list]:
    """12 x 8 m house, 4 m walls, gable roof of the pitch: ridge, eaves, rakes and wall
    corners are creases."""
    L, W, H = 12.0, 8.0, 4.0
    R = H + W / 2 * np.tan(np.radians(pitch_deg))
    c = np.array([(0, 0, 0), (L, 0, 0), (L, W, 0), (0, W, 0),
                  (0, 0, H), (L, 0, H), (L, W, H), (0, W, H)], float)
    r0, r1 = np.array([0, W / 2, R]), np.array([L, W / 2, R])
    tris = (_quad(c[0], c[1], c[5], c[4]) + _quad(c[2], c[3], c[7], c[6])
            + _quad(c[1], c[2], c[6], c[5]) + _quad(c[3], c[0], c[4], c[7])
            + [[c[5], c[6], r1], [c[7], c[4], r0]]
            + _quad(c[4], c[5], r1, r0) + _quad(c[6], c[7], r0, r1))
    edges = [(r0, r1), (c[4], c[5]), (c[6], c[7]), (c[4], r0), (c[7], r0), (c[5], r1),
             (c[6], r1), (c[0], c[4]), (c[1], c[5]), (c[2], c[6]), (c[3], c[7])]
    return _sample_triangles(np.array(tris), rng), edges


def tower(rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """30 m lattice tower: 4 legs from a 6 m to a 2 m square, X braces every 5 m; points
    spread along the members (every SPACING) and around them (0.1 m members)."""
    levels = np.linspace(0, 30, 7)
    half = np.interp(levels, [0, 30], [3.0, 1.0])
    corners = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], float)
    ring = [np.column_stack([corners * h, np.full(4, z)]) for h, z in zip(half, levels)]
    edges = []
    for i in range(len(levels) - 1):
        for j in range(4):
            a0, a1 = ring[i][j], ring[i][(j + 1) % 4]
            b0, b1 = ring[i + 1][j], ring[i + 1][(j + 1) % 4]
            edges += [(a0, b0), (a0, b1), (a1, b0)]
    pts = []
    for a, b in edges:
        n = max(2, int(np.linalg.norm(b - a) / SPACING))
        t = rng.random(n)
        pts.append(a + t[:, None] * (b - a) + rng.normal(0, 0.05, (n, 3)))
    return np.concatenate(pts), edges


def wire(rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """A 60 m span sagging 2 m, points every ~0.3 m with 0.02 m noise (a wire seen from
    the air)."""
    x = np.sort(rng.uniform(0, 60, 200))
    z = 20 - 2 + 2 * ((x - 30) / 30) ** 2
    pts = np.column_stack([x, np.zeros_like(x), z]) + rng.normal(0, 0.02, (len(x), 3))
    xs = np.linspace(0, 60, 121)
    line = np.column_stack([xs, np.zeros_like(xs), 18 + 2 * ((xs - 30) / 30) ** 2])
    return pts, list(zip(line[:-1], line[1:]))


def crown(rng: np.random.Generator, centre) -> np.ndarray:
    """A tree crown seen from the air: leaves in the outer 40 % of a 3 x 3 x 2.5 m
    (semi-axes) ellipsoid, about DENSITY points per m^2 of its surface. No feature lines."""
    n = int(4 * np.pi * 3.0 * 2.8 * DENSITY)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = rng.uniform(0.6 ** 3, 1.0, n) ** (1 / 3)
    return u * r[:, None] * [3.0, 3.0, 2.5] + np.asarray(centre, float)


def scene(rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """What an obstacle cloud holds: the box and a 20 deg gable house with two tree crowns
    beside them. The crowns' points lie far from every edge: found, they are false."""
    b_xyz, b_edges = box(rng)
    g_xyz, g_edges = gable(rng, 20.0)
    shift = np.array([20.0, 0.0, 0.0])
    xyz = np.concatenate([b_xyz, g_xyz + shift, crown(rng, (2.0, 16.0, 8.0)),
                          crown(rng, (26.0, 16.0, 7.0))])
    return xyz, b_edges + [(a + shift, b + shift) for a, b in g_edges]


def distance_to_edges(p: np.ndarray, edges: list) -> np.ndarray:
    d = np.full(len(p), np.inf)
    for a, b in edges:
        ab = b - a
        t = np.clip(((p - a) @ ab) / (ab @ ab), 0, 1)
        d = np.minimum(d, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
    return d


# --------------------------------------------------------------------------- methods


def surface_variation(xyz: np.ndarray, k: int) -> np.ndarray:
    """The anchor: l3 / (l1 + l2 + l3) of the point and its k nearest neighbours."""
    _, idx = cKDTree(xyz).query(xyz, k + 1, workers=-1)
    nb = xyz[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    values = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred))
    return values[:, 0] / np.maximum(values.sum(axis=1), 1e-30)


def anchor(xyz: np.ndarray, k: int, share: float) -> np.ndarray:
    """Feature points of the anchor: the `share` of points of highest surface variation."""
    var = surface_variation(xyz, k)
    n = int(round(share * len(xyz)))
    out = np.zeros(len(xyz), bool)
    if n:
        out[np.argsort(-var, kind="stable")[:n]] = True
    return out


def run(xyz: np.ndarray, cfg: FeaturesConfig) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    res = gaussian_map_features(xyz, cfg=cfg, rng=np.random.default_rng(cfg.seed))
    return res.feature, time.perf_counter() - t


def scores(feature: np.ndarray, dist: np.ndarray) -> tuple[float, float]:
    precision = float((dist[feature] <= PRECISION_BAND).mean()) if feature.any() else float("nan")
    truth = dist <= RECALL_BAND
    recall = float(feature[truth].mean()) if truth.any() else float("nan")
    return precision, recall


# --------------------------------------------------------------------------- (a)


SHAPES = {"box": box, "gable 20 deg": lambda r: gable(r, 20.0),
          "gable 45 deg": lambda r: gable(r, 45.0), "tower": tower, "wire": wire,
          "houses + crowns": scene}


def synthetic(noises: list[float], names: list[str]) -> list[dict]:
    base = FeaturesConfig()
    rows = []
    for noise in noises:
        for name in names:
            make = SHAPES[name]
            rng = np.random.default_rng(7)
            xyz, edges = make(rng)
            if name not in ("tower", "wire"):
                xyz = xyz + rng.normal(0, noise, xyz.shape)
            dist = distance_to_edges(xyz, edges)
            found = {}
            for method in ("faithful", "fast"):
                feature, sec = run(xyz, replace(base, method=method))
                found[method] = feature
                p, r = scores(feature, dist)
                rows.append({"shape": name, "noise_m": noise, "points": len(xyz),
                             "method": method, "share": float(feature.mean()),
                             "precision": p, "recall": r, "seconds": sec})
            t = time.perf_counter()
            feature = anchor(xyz, base.neighbours, float(found["fast"].mean()))
            sec = time.perf_counter() - t
            p, r = scores(feature, dist)
            rows.append({"shape": name, "noise_m": noise, "points": len(xyz),
                         "method": "anchor PCA", "share": float(feature.mean()),
                         "precision": p, "recall": r, "seconds": sec})
            agree = float((found["fast"] == found["faithful"]).mean())
            for row in rows[-3:]:
                row["agree_fast_faithful"] = agree
    return rows


# --------------------------------------------------------------------------- (b)


def real(limit: int | None) -> list[dict]:
    sets = {}
    path = DATA / "ahn4" / "ahn_2496_9727.laz"
    if path.is_file():
        las = read_las(path)
        sets["AHN4 buildings (class 6)"] = las.xyz[las.points["classification"] == 6]
    path = DATA / "ahn-corridor" / "07CZ2_14.laz"
    if path.is_file():
        las = read_las(path)
        cls = las.points["classification"]
        centre = las.xyz[cls == 15].mean(axis=0)
        near = np.hypot(*(las.xyz[:, :2] - centre[:2]).T) <= 40.0
        sets["corridor crop (towers, wires, trees)"] = las.xyz[near & ~np.isin(cls, [2, 9])]
    rows = []
    base = FeaturesConfig()
    for name, xyz in sets.items():
        if limit and len(xyz) > limit:  # the `limit` points nearest the middle
            mid = np.median(xyz[:, :2], axis=0)
            xyz = xyz[np.argsort(np.hypot(*(xyz[:, :2] - mid).T))[:limit]]
        found = {}
        for method in ("faithful", "fast"):
            feature, sec = run(xyz, replace(base, method=method))
            found[method] = feature
            rows.append({"data": name, "points": len(xyz), "method": method,
                         "feature_points": int(feature.sum()), "share": float(feature.mean()),
                         "seconds": sec, "ms_per_10k": 1e3 * sec / len(xyz) * 1e4})
        agree = float((found["fast"] == found["faithful"]).mean())
        for row in rows[-2:]:
            row["agree_fast_faithful"] = agree
    rows.append({"data": "paper: sculpture (Xu et al. 2019, table 1)",
                 "points": PAPER["points"], "method": "paper",
                 "feature_points": PAPER["feature_points"], "share": PAPER["share"],
                 "seconds": PAPER["seconds"],
                 "ms_per_10k": 1e3 * PAPER["seconds"] / PAPER["points"] * 1e4,
                 "agree_fast_faithful": float("nan")})
    return rows


def main() -> None:
    args = bench_args(__doc__, "one noise level, 10k real points",
                      "one noise level, three shapes, 2k real points")
    noises = per_mode(args, [0.0, 0.02, 0.05], [0.02], [0.02])
    # smoke: a noisy surface shape and the two line shapes, which are left without noise
    syn = synthetic(noises, per_mode(args, list(SHAPES), list(SHAPES), ["box", "tower", "wire"]))
    print("## (a) synthetic shapes with known edges\n")
    print(f"precision within {PRECISION_BAND:.2f} m of a true edge, recall of points within "
          f"{RECALL_BAND:.2f} m; {DENSITY:g} pts/m^2\n")
    print("| shape | noise m | points | method | share | precision | recall | s | agree |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in syn:
        print(f"| {r['shape']} | {r['noise_m']:.2f} | {r['points']} | {r['method']} | "
              f"{r['share']:.3f} | {r['precision']:.3f} | {r['recall']:.3f} | "
              f"{r['seconds']:.2f} | {r['agree_fast_faithful']:.3f} |")
    rl = real(per_mode(args, None, 10000, 2000))
    print("\n## (b) real data\n")
    print("| data | points | method | feature points | share | s | ms / 10k pts | agree |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rl:
        print(f"| {r['data']} | {r['points']} | {r['method']} | {r['feature_points']} | "
              f"{r['share']:.4f} | {r['seconds']:.2f} | {r['ms_per_10k']:.0f} | "
              f"{r['agree_fast_faithful']:.3f} |")
    out = {"quick": args.quick, "machine": platform.platform(), "python": platform.python_version(),
           "config": {k: getattr(FeaturesConfig(), k) for k in FeaturesConfig.__dataclass_fields__},
           "synthetic": syn, "real": rl}
    (args.out / "features.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
