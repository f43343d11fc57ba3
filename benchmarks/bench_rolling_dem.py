"""The rolling DEM of simulated flights against the true terrain: what `dem_builder` (and
`replay`) publish, built from the detector's ground, and from the simulator's reference
ground labels as the anchor (a perfect ground filter, the same DEM pipeline).

Usage: .venv/bin/python benchmarks/bench_rolling_dem.py [--quick | --smoke --out DIR]

Each flight (10 Hz, ~50 000 points a message, 10 s; 5 s and two scenes with --quick, 1 s
and one scene with --smoke) goes
through `DemPipeline` with the default `DemBuilderConfig` (1 m cells, kriging, thinning,
the 200 m window following the vehicle): `process` (the detector's ground, as the node
finds it) or `add_ground` of the points labelled 2. The DEM after the last message is
compared with the simulator's terrain (`scene_ground_height`) at the cell centres:
measured cells (RMSE, and how many are more than 1 m off: ground taken from objects or
from noise echoes), and the cells filled by interpolation, by their distance from the
nearest measured cell (within 2, 2-4, 4-8, 8-20 m). Writes benchmarks/results/rolling_dem.json
(to --out DIR if given).
"""
from __future__ import annotations

import json

import numpy as np
from scipy import ndimage

from lidar_obstacles.config import DemBuilderConfig
from lidar_obstacles.core.pipeline import DemPipeline
from lidar_obstacles.core.simulate import SimSettings, scene_ground_height, simulate_flight
from common import bench_args, per_mode, table  # (benchmarks/ is on the path)

SCENES = ("mixed", "corridor", "urban", "forest")
BANDS = ((0.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 20.0))  # m from the nearest measured cell


def rolling_dem(settings: SimSettings, source: str):
    """The DEM grid after the flight; source "detector" or "reference"."""
    pipe = DemPipeline(DemBuilderConfig())
    for frame in simulate_flight(settings):
        p = frame.points
        xyz = np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64)
        if source == "detector":
            pipe.process(xyz, stamp=frame.stamp, vehicle_xyz=frame.position)
        else:
            pipe.add_ground(xyz[p["classification"] == 2], stamp=frame.stamp,
                            vehicle_xyz=frame.position)
    return pipe.dem.snapshot()


def score(grid, settings: SimSettings) -> dict:
    """Errors (m) of the grid's cells against the true terrain."""
    rows, cols = np.nonzero(np.isfinite(grid.elevation))
    xy = np.asarray(grid.origin) + (np.column_stack([cols, rows]) + 0.5) * grid.resolution
    error = np.full(grid.elevation.shape, np.nan)
    error[rows, cols] = grid.elevation[rows, cols] - scene_ground_height(settings, xy)
    measured = grid.count > 0
    filled = grid.interpolated.astype(bool)
    away = ndimage.distance_transform_edt(~measured) * grid.resolution

    def rmse(mask: np.ndarray) -> float | None:
        return float(np.sqrt(np.mean(error[mask] ** 2))) if mask.any() else None

    out = {"measured_cells": int(measured.sum()), "measured_rmse_m": rmse(measured),
           "measured_off_1m": int((np.abs(error[measured]) > 1.0).sum())}
    for lo, hi in BANDS:
        out[f"filled_{lo:g}_{hi:g}m_rmse"] = rmse(filled & (away > lo) & (away <= hi))
    near = filled & (away <= 4.0)
    out["filled_4m_off_1m_pct"] = (100.0 * float(np.mean(np.abs(error[near]) > 1.0))
                                   if near.any() else None)
    return out


def main() -> int:
    args = bench_args(__doc__, "5 s flights, two scenes", "a 1 s flight, one scene")
    seconds = per_mode(args, 10.0, 5.0, 1.0)
    rows = []
    for scene in per_mode(args, SCENES, SCENES[:2], SCENES[:1]):
        settings = SimSettings(scene=scene, seed=1, duration=seconds, frame="map")
        for source in ("reference", "detector"):
            rows.append({"flight": f"{scene} {seconds:g} s", "ground": source,
                         **score(rolling_dem(settings, source), settings)})
    cols = ["flight", "ground", "measured_cells", "measured_rmse_m", "measured_off_1m"]
    cols += [f"filled_{lo:g}_{hi:g}m_rmse" for lo, hi in BANDS] + ["filled_4m_off_1m_pct"]
    print("Rolling DEM (default dem_builder settings) minus the true terrain, m; filled "
          "cells by their distance from the nearest measured cell\n")
    print(table(rows, cols))
    (args.out / "rolling_dem.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"\nwrote {args.out / 'rolling_dem.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
