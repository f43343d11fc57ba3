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

# The classes' colours in the markers and in every picture of the report (the usual ASPRS
# viewer scheme: brown ground, greens, orange-red buildings, cyan wires, magenta towers).
CLASS_HEX: dict[int, str] = {
    UNCLASSIFIED: "#5b6b7d", GROUND: "#a0522d", LOW_VEGETATION: "#b5d96a",
    MEDIUM_VEGETATION: "#5fae3c", HIGH_VEGETATION: "#1e6b2a", BUILDING: "#e8541e",
    NOISE: "#a8a8a8", WIRE: "#00c8e0", TOWER: "#e000e0",
}
# ... as RGB in 0..1 (std_msgs/ColorRGBA's)
CLASS_COLOURS: dict[int, tuple[float, float, float]] = {
    code: tuple(int(h[i:i + 2], 16) / 255.0 for i in (1, 3, 5))  # type: ignore[misc]
    for code, h in CLASS_HEX.items()}


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
