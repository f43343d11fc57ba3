"""Make the README's pictures of the real data in ../shared/data:

- simplify_features.png: the AHN4 tile, its simplified cloud and the feature points of
  its buildings (what `lidar-obstacles simplify` and `features` give);
- the pictures `lidar-obstacles evaluate --report` draws, for three files: the errors on
  ISPRS samp11 (isprs_samp11_errors.png) and its kappa per block
  (isprs_samp11_blocks.png), the classes of a power-line corridor tile
  (corridor_classes.png), and the error of samp11's DEM from the detected ground
  against the DEM of the reference ground (isprs_samp11_dem_error.png). They are stored
  with a 256-colour palette: a quarter of the size, no visible difference;
- urban_roof_islands.png: one message of the simulator's urban flight (seed 1), whose
  roofs at the strip's edges the opening alone takes for ground, and the raised-island
  test (HybridSettings.island_rise) takes back out;
- dem_edge_echoes.png: the rolling DEM of the simulator's mixed flight (10 s, seed 1)
  against the true terrain, without and with the test of lone low echoes beyond the
  strips' edges (HybridSettings.lone_reach);
- isprs_samp11_streamed.png: ISPRS samp11 streamed in `las2bag`'s 10 m strips through
  the detector, and the share of its ground taken for objects by depth in the strip.

    .venv/bin/python docs/figures.py
"""
from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402
from scipy import ndimage  # noqa: E402

import lidar_obstacles.core.ground as ground_module  # noqa: E402
from lidar_obstacles.config import DemBuilderConfig, FeaturesConfig, SimplifyConfig  # noqa: E402
from lidar_obstacles.core.features import gaussian_map_features  # noqa: E402
from lidar_obstacles.core.ground import HybridSettings, morphological_ground  # noqa: E402
from lidar_obstacles.core.pipeline import DemPipeline  # noqa: E402
from lidar_obstacles.core.simulate import (SimSettings, scene_ground_height,  # noqa: E402
                                           simulate_flight)
from lidar_obstacles.core.simplify import simplify  # noqa: E402
from lidar_obstacles.evaluate import evaluate  # noqa: E402
from lidar_obstacles.io.las import read_las  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data"


# (input, its report's picture, the name here)
REPORT_PICTURES = [
    ("isprs/samp11-utm.laz", "errors.png", "isprs_samp11_errors.png"),
    ("isprs/samp11-utm.laz", "block_kappa.png", "isprs_samp11_blocks.png"),
    ("ahn-corridor/07CZ2_14.laz", "classes.png", "corridor_classes.png"),
    ("isprs/samp11-utm.laz", "dem_error.png", "isprs_samp11_dem_error.png"),
]


def report_pictures() -> None:
    """Each input's evaluation report, and the pictures kept from it."""
    for src in dict.fromkeys(src for src, _, _ in REPORT_PICTURES):
        with tempfile.TemporaryDirectory() as tmp:
            metrics = evaluate(DATA / src, report_dir=tmp)
            print(src, "kappa", round(metrics["ground_object"]["kappa"], 3))
            for _, picture, name in (r for r in REPORT_PICTURES if r[0] == src):
                with Image.open(Path(tmp) / picture) as im:
                    im.convert("RGB").quantize(256).save(HERE / name, optimize=True)
                print(HERE / name)


def save_quantized(fig: plt.Figure, name: str) -> None:
    """Save a figure here with a 256-colour palette."""
    with tempfile.TemporaryDirectory() as tmp:
        fig.savefig(Path(tmp) / name, dpi=110)
        with Image.open(Path(tmp) / name) as im:
            im.convert("RGB").quantize(256).save(HERE / name, optimize=True)
    print(HERE / name)


def island_picture(message: int = 94) -> None:
    """One urban message filtered alone, without and with the raised-island test."""
    frames = simulate_flight(SimSettings(scene="urban", seed=1, duration=(message + 1) / 10,
                                         frame="map"))
    points = list(frames)[message].points
    xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64)
    building = points["classification"] == 6
    fig, axes = plt.subplots(1, 2, figsize=(10, 7.5), constrained_layout=True)
    for ax, (settings, label) in zip(axes, [(HybridSettings(island_rise=0.0), "opening alone"),
                                            (HybridSettings(), "with the island test")]):
        ground, _ = morphological_ground(xyz - xyz.mean(axis=0), settings)
        for mask, colour, name in [(ground & ~building, "#4c9a2a", "ground"),
                                   (~ground & ~building, "0.6", "other objects"),
                                   (building & ~ground, "#f0a030", "building"),
                                   (building & ground, "#d62728", "building taken for ground")]:
            ax.scatter(xyz[mask, 0], xyz[mask, 1], s=0.4, c=colour, lw=0,
                       label=f"{name}: {mask.sum():,}")
        ax.set_title(f"{label}: {100 * ground[building].mean():.0f} % of the roof "
                     f"points in ground", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.legend(loc="upper left", fontsize=8, markerscale=12, framealpha=0.9)
    axes[0].set_ylabel("y (m)")
    save_quantized(fig, "urban_roof_islands.png")


def rolling_dem(settings: SimSettings, hybrid: HybridSettings):
    """The rolling DEM (`dem_builder`'s, from the detector's ground) after the flight, its
    ground filtered with `hybrid` in place of the defaults."""
    default = ground_module.HybridSettings
    # classify_ground builds its settings from the config's few ground parameters; the
    # others (here lone_reach) are the class's defaults, so the class is swapped.
    ground_module.HybridSettings = lambda **kw: dataclasses.replace(hybrid, **kw)
    try:
        dem = DemPipeline(DemBuilderConfig())
        for frame in simulate_flight(settings):
            p = frame.points
            dem.process(np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64),
                        stamp=frame.stamp, vehicle_xyz=frame.position)
        return dem.dem.snapshot()
    finally:
        ground_module.HybridSettings = default


def dem_echo_picture() -> None:
    """The mixed flight's rolling DEM minus the true terrain, without and with the test of
    lone low echoes beyond the strips' edges."""
    settings = SimSettings(scene="mixed", seed=1, duration=10.0, frame="map")
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), constrained_layout=True)
    for ax, (hybrid, label) in zip(axes, [(HybridSettings(lone_reach=0.0), "without"),
                                          (HybridSettings(), "with")]):
        grid = rolling_dem(settings, hybrid)
        rows, cols = np.nonzero(np.isfinite(grid.elevation))
        xy = grid.origin + (np.column_stack([cols, rows]) + 0.5) * grid.resolution
        error = np.full(grid.elevation.shape, np.nan)
        error[rows, cols] = grid.elevation[rows, cols] - scene_ground_height(settings, xy)
        filled = grid.interpolated.astype(bool)
        near = filled & (ndimage.distance_transform_edt(grid.count == 0)
                         * grid.resolution <= 4.0)
        rmse = float(np.sqrt(np.nanmean(error[near] ** 2)))
        height, width = np.array(grid.elevation.shape) * grid.resolution
        extent = (grid.origin[0], grid.origin[0] + width, grid.origin[1],
                  grid.origin[1] + height)
        im = ax.imshow(error, origin="lower", cmap="RdBu", vmin=-5, vmax=5, extent=extent)
        ax.set_title(f"{label} the lone-echo test\ncells filled within 4 m of the data: "
                     f"RMSE {rmse:.2f} m", fontsize=10)
        ax.set_xlabel("x (m)")
    axes[0].set_ylabel("y (m)")
    fig.colorbar(im, ax=axes, shrink=0.8, label="DEM - true terrain (m)")
    save_quantized(fig, "dem_edge_echoes.png")


def streamed_edge_picture(strip: float = 10.0) -> None:
    """ISPRS samp11 streamed as `las2bag` cuts it (strips `strip` m deep across its length,
    south to north) through the detector, against the file whole: where the ground is
    taken for objects, and how that share grows towards each strip's leading edge."""
    from lidar_obstacles.config import ObstacleDetectorConfig
    from lidar_obstacles.evaluate import load_input, run_detector
    from lidar_obstacles.ros.offline import las2bag

    src = DATA / "isprs" / "samp11-utm.laz"
    with tempfile.TemporaryDirectory() as tmp:
        las2bag(src, Path(tmp) / "bag", strip_width=strip)
        inp = load_input(Path(tmp) / "bag")
        run_detector(inp, ObstacleDetectorConfig())
    xyz = np.concatenate([c.xyz for c in inp.clouds])
    ref = np.concatenate([c.reference for c in inp.clouds]) == 2
    ground = np.concatenate([c.predicted for c in inp.clouds]) == 2
    # depth in its strip (m from the strip's southern, trailing edge)
    depth = np.concatenate([c.xyz[:, 1] - c.xyz[:, 1].min() for c in inp.clouds])
    whole = evaluate(src)  # (its figures, for the title)
    fig, (top, share) = plt.subplots(1, 2, figsize=(11, 7.5), width_ratios=(1.1, 1),
                                     constrained_layout=True)
    lo = xyz.min(axis=0)
    type1, type2 = ref & ~ground, ~ref & ground
    top.scatter(*(xyz[:, :2] - lo[:2]).T, s=0.3, c="0.85", lw=0)
    top.scatter(*(xyz[type2, :2] - lo[:2]).T, s=1.2, c="#1f77b4", lw=0,
                label=f"object taken for ground: {type2.sum():,}")
    top.scatter(*(xyz[type1, :2] - lo[:2]).T, s=1.2, c="#d62728", lw=0,
                label=f"ground taken for objects: {type1.sum():,}")
    for c in inp.clouds[1:]:
        top.axhline(c.xyz[:, 1].min() - lo[1], c="0.5", lw=0.3)
    total = 100 * (type1.sum() + type2.sum()) / len(ref)
    top.set_title(f"samp11 in {len(inp.clouds)} strips of {strip:g} m, streamed: total "
                  f"error {total:.1f} %\n(the file whole: "
                  f"{100 * whole['ground_object']['total_error']:.1f} %)", fontsize=10)
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m), the strips' order: south to north, uphill")
    top.legend(loc="upper left", fontsize=8, markerscale=8, framealpha=0.9)
    bins = np.arange(0.0, strip + 1.0)
    counts = np.histogram(depth[ref], bins)[0]
    missed = np.histogram(depth[type1], bins)[0]
    share.bar(bins[:-1] + 0.5, 100 * missed / np.maximum(counts, 1), width=0.8,
              color="#d62728")
    share.set_xlabel("depth in the strip (m): trailing edge, next to what came before, "
                     "at 0;\nleading edge, with nothing yet beyond it, at the right")
    share.set_ylabel("reference ground taken for objects (%)")
    share.set_title("a slope rising past the leading edge looks, from one side, like a "
                    "roof\ncut by it: the opening lowers it there", fontsize=10)
    save_quantized(fig, "isprs_samp11_streamed.png")


def main() -> None:
    report_pictures()
    island_picture()
    dem_echo_picture()
    streamed_edge_picture()
    las = read_las(DATA / "ahn4" / "ahn_2496_9727.laz")
    xyz, pts = las.xyz, las.points
    simple = simplify(xyz, cfg=SimplifyConfig(), return_number=pts["return_number"],
                      rng=np.random.default_rng(0))
    building = pts["classification"] == 6
    edges = np.zeros(len(xyz), bool)
    edges[building] = gaussian_map_features(xyz[building], cfg=FeaturesConfig(),
                                            rng=np.random.default_rng(0)).feature
    lo = xyz.min(axis=0)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.4), constrained_layout=True)
    views = [(np.ones(len(xyz), bool), f"AHN4 tile: {len(xyz):,} points"),
             (simple.keep, f"simplify (normal_space): {simple.keep.sum():,} kept "
                           f"({100 * simple.keep.mean():.0f} %)"),
             (edges, f"features of the buildings: {edges.sum():,} of {building.sum():,} "
                     f"points")]
    for ax, (mask, title) in zip(axes, views):
        if mask is edges:
            ax.scatter(*(xyz[building][:, :2] - lo[:2]).T, s=0.3, c="0.85", lw=0)
        sc = ax.scatter(*(xyz[mask][:, :2] - lo[:2]).T, s=0.6 if mask is edges else 0.3,
                        c=xyz[mask, 2], cmap="viridis", lw=0)
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    axes[0].set_ylabel("y (m)")
    fig.colorbar(sc, ax=axes, shrink=0.8, label="z (m)")
    out = HERE / "simplify_features.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
