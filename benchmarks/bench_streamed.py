"""The real surveys streamed as a scanner would send them, against the same files whole.

Each AHN file (and ISPRS samp11) is cut by `las2bag` with its defaults (slices of 0.1 s
of GPS time when the file has it, else 10 m strips) and run through the detector message
by message, as `lidar-obstacles evaluate BAG` does: each slice sees only the slices before
it (the ground context, the remembered towers, wires and buildings, and a thin strip's
shape context). The same file as one cloud is the ceiling. Ground kappa, wire / tower /
building recall and precision, the obstacle points taken for ground, and the corridor's
cranes (class 26) found as unclassified structures (1).

    python benchmarks/bench_streamed.py [--quick | --smoke --out DIR]

--smoke streams the 3 000 AHN4 points nearest its middle (0.1 s slices) and ISPRS samp24
(7 492 points, 10 m strips). Writes benchmarks/results/streamed.json (to --out DIR if
given).
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from lidar_obstacles.evaluate import evaluate
from lidar_obstacles.io.las import read_las, write_las_subset
from lidar_obstacles.ros.offline import las2bag
from common import bench_args, per_mode, table  # (benchmarks/ is on the path)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
FILES = ["ahn4/ahn_2496_9727.laz", "ahn-corridor/07CZ2_14.laz", "ahn-corridor/12AN2_20.laz",
         "isprs/samp11-utm.laz"]
SMOKE = {"ahn4/ahn_2496_9727.laz": 3000, "isprs/samp24-utm.laz": None}  # points kept
CLASSES = ("wire", "tower", "building")
CRANE, UNCLASSIFIED = "26", "1"  # the corridor's inserted cranes; structures are class 1


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
    crane = metrics["by_code"].get(CRANE)
    if crane:
        row["cranes unclassified %"] = 100.0 * crane.get(UNCLASSIFIED, 0) / sum(crane.values())
    blocks = metrics["blocks"]
    if blocks and blocks["n_eligible"]:
        row["6x6 blocks kappa > 0.8 %"] = 100.0 * blocks["share_kappa_gt_0_8"]
    return row


def middle(src: Path, n: int, out: Path) -> Path:
    """`out`: the n points of `src` nearest (in XY) to its median point, as a LAS file."""
    xy = read_las(src).xyz[:, :2]
    dist = np.hypot(*(xy - np.median(xy, axis=0)).T)
    keep = np.zeros(len(xy), bool)
    keep[np.argpartition(dist, n - 1)[:n]] = True
    write_las_subset(src, keep, out)
    return out


def main() -> None:
    args = bench_args(__doc__, "AHN4 only", "an AHN4 crop and the smallest ISPRS sample")
    files = per_mode(args, dict.fromkeys(FILES), dict.fromkeys(FILES[:1]), SMOKE)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rel, n in files.items():
            src = DATA / rel if n is None else middle(DATA / rel, n, Path(tmp) / Path(rel).name)
            bag = Path(tmp) / src.stem
            las2bag(src, bag)
            for how, path in (("whole", src), ("streamed", bag)):
                rows.append({"file": rel, "as": how,
                             **figures(evaluate(path, with_dem=False))})
    cols = ["file", "as", "clouds", "ground kappa", "total error %", "wire recall",
            "wire precision", "tower recall", "tower precision", "building recall",
            "building precision", "wire+tower as ground %", "6x6 blocks kappa > 0.8 %",
            "cranes unclassified %"]
    print(table(rows, cols))
    (args.out / "streamed.json").write_text(json.dumps(rows, indent=2, default=float))


if __name__ == "__main__":
    main()
