"""`lidar-obstacles demo`: the main job on the embedded default.

Simulates a labelled UAV flight over a scene with ground, trees, buildings, towers and power
lines; runs both nodes' pipelines on it (`replay`); exports the DEM as GeoTIFF with a
hillshade; evaluates the result against the simulator's truth with a report of pictures.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from lidar_obstacles.errors import OutputError


def run_demo(out: Path, *, scene: str = "mixed", duration: float = 20.0, seed: int = 0,
             say: Callable[[str], None] = lambda line: None) -> dict:
    """Simulate, replay, export and evaluate into folder `out`; `say` is told each step and,
    at the end, where the outputs are (the CLI prints them on stderr). Returns the summary:
    the outputs' paths and the headline figures."""
    from lidar_obstacles.evaluate import evaluate
    from lidar_obstacles.ros import offline

    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a folder: not overwriting it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # (a file on the way, no permission)
        raise OutputError(f"cannot make the output folder {out}: {exc.strerror}") from None
    flight, replayed = out / "flight", out / "replayed"
    dem_tif, report = out / "dem.tif", out / "report"
    steps = [f"1/4 simulating a {duration:g} s flight over the '{scene}' scene",
             "2/4 running obstacle_detector and dem_builder on it (replay)",
             "3/4 exporting the DEM", "4/4 evaluating against the simulator's truth"]
    say(steps[0])
    sim = offline.simulate(flight, scene=scene, seed=seed, duration=duration, frame="map")
    say(steps[1])
    rep = offline.replay(flight, replayed)
    say(steps[2])
    dem = offline.export_dem(flight, dem_tif)
    say(steps[3])
    metrics = evaluate(replayed, report_dir=report)
    summary = {
        "flight_bag": str(flight), "output_bag": str(replayed), "dem_geotiff": str(dem_tif),
        "dem_hillshade": dem["hillshade"], "report": str(report / "report.html"),
        "messages": sim["messages"], "points": sim["points"],
        "real_time_factor": rep["real_time_factor"], "latency_p95_ms": rep["latency_p95_ms"],
        "ground_kappa": metrics["ground_object"]["kappa"],
        "total_error": metrics["ground_object"]["total_error"],
        "wire_recall": metrics["per_class"]["wire"]["producers_accuracy"],
        "tower_recall": metrics["per_class"]["tower"]["producers_accuracy"],
        "wire_tower_in_ground": metrics["safety"]["obstacle_as_ground"],
    }
    say(f"\nDemo done. Open {report / 'report.html'} for the pictures; outputs in {out}/")
    return summary
