"""The real surveys streamed as a scanner would send them, against the same files whole.

Each AHN file (and ISPRS samp11) is cut by `las2bag` with its defaults (slices of 0.1 s
of GPS time when the file has it, else 10 m strips) and run through the detector message
by message, as `lidar-obstacles evaluate BAG` does: each slice sees only the slices before
it (the ground context, the remembered towers, wires and buildings, and a thin strip's
shape context). The same file as one cloud is the ceiling. Ground kappa, wire / tower /
building recall and precision, and the obstacle points taken for ground.

    python benchmarks/bench_streamed.py [--quick]
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

from lidar_obstacles.evaluate import evaluate
from lidar_obstacles.ros.offline import las2bag
from common import quick_args, table  # (benchmarks/ is on the path)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
FILES = ["ahn4/ahn_2496_9727.laz", "ahn-corridor/07CZ2_14.laz", "ahn-corridor/12AN2_20.laz",
         "isprs/samp11-utm.laz"]
CLASSES = ("wire", "tower", "building")


def figures(metrics: dict) -> dict:
    """The row of one evaluation: ground kappa, per-class recall / precision, safety."""
    row = {"clouds": metrics["clouds"],
           "ground kappa": metrics["ground_object"]["kappa"],
           "total error %": 100.0 * metrics["ground_object"]["total_error"]}
    for name in CLASSES:
        per = metrics["per_class"][name]
        if per.get("reference_count"):
            row[f"{name} recall"] = per["producers_accuracy"]
        if per.get("predicted_count"):
            row[f"{name} precision"] = per["users_accuracy"]
    unsafe = metrics["safety"]["obstacle_as_ground"]
    if unsafe is not None:
        row["wire+tower as ground %"] = 100.0 * unsafe
    blocks = metrics["blocks"]
    if blocks and blocks["n_eligible"]:
        row["6x6 blocks kappa > 0.8 %"] = 100.0 * blocks["share_kappa_gt_0_8"]
    return row


def main() -> None:
    args = quick_args(__doc__, "AHN4 only")
    files = FILES[:1] if args.quick else FILES
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rel in files:
            src = DATA / rel
            bag = Path(tmp) / src.stem
            las2bag(src, bag)
            for how, path in (("whole", src), ("streamed", bag)):
                rows.append({"file": rel, "as": how,
                             **figures(evaluate(path, with_dem=False))})
    cols = ["file", "as", "clouds", "ground kappa", "total error %", "wire recall",
            "wire precision", "tower recall", "tower precision", "building recall",
            "building precision", "wire+tower as ground %", "6x6 blocks kappa > 0.8 %"]
    print(table(rows, cols))
    (REPO / "benchmarks" / "results").mkdir(parents=True, exist_ok=True)
    (REPO / "benchmarks" / "results" / "streamed.json").write_text(
        json.dumps(rows, indent=2, default=float))


if __name__ == "__main__":
    main()
