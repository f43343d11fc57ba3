"""ASPRS classification codes used in the `class` field (the contract's list)."""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where it is used, not at import time
    import numpy as np

UNCLASSIFIED = 1  # obstacle of no other class: pole, vehicle, crane...
GROUND = 2
LOW_VEGETATION = 3  # < 0.5 m above ground
MEDIUM_VEGETATION = 4  # 0.5-2 m
HIGH_VEGETATION = 5  # > 2 m
BUILDING = 6
NOISE = 7
WIRE = 14  # wire conductor
TOWER = 15  # transmission tower

CLASS_NAMES: dict[int, str] = {
    UNCLASSIFIED: "unclassified", GROUND: "ground", LOW_VEGETATION: "low_vegetation",
    MEDIUM_VEGETATION: "medium_vegetation", HIGH_VEGETATION: "high_vegetation",
    BUILDING: "building", NOISE: "noise", WIRE: "wire", TOWER: "tower",
}

# RGB in 0..1 of the markers, the report's palette (report.CLASS_STYLE): brown ground, greens,
# red buildings, cyan wires, magenta towers.
CLASS_COLOURS: dict[int, tuple[float, float, float]] = {
    UNCLASSIFIED: (0.6, 0.6, 0.6), GROUND: (0.55, 0.4, 0.25), LOW_VEGETATION: (0.6, 0.85, 0.4),
    MEDIUM_VEGETATION: (0.3, 0.7, 0.2), HIGH_VEGETATION: (0.05, 0.45, 0.1),
    BUILDING: (0.85, 0.2, 0.15), NOISE: (0.3, 0.3, 0.3), WIRE: (0.0, 0.78, 0.88),
    TOWER: (0.85, 0.1, 0.85),
}


def vegetation_class(height_above_ground: np.ndarray | float) -> np.ndarray:
    """ASPRS vegetation code by height above ground.

    height_above_ground: (N,) float (or any shape, or a scalar), metres. Returns a uint8
    array of the same shape: LOW_VEGETATION below 0.5 m, MEDIUM_VEGETATION 0.5-2 m
    (inclusive), HIGH_VEGETATION above 2 m.
    """
    import numpy as np

    h = np.asarray(height_above_ground)
    return np.where(h < 0.5, LOW_VEGETATION,
                    np.where(h <= 2.0, MEDIUM_VEGETATION, HIGH_VEGETATION)).astype(np.uint8)
