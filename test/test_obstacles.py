"""Obstacle classes on synthetic scenes with known answers, and the clearance grid."""
from __future__ import annotations

import numpy as np

from lidar_obstacles.config import ObstacleDetectorConfig
from lidar_obstacles.core.obstacles import classify_obstacles, clearance_grid

CFG = ObstacleDetectorConfig()


def _scene(rng):
    """Flat ground at z=0, a wire span between two lattice towers, trees under it, a box
    building, a pole and an isolated point in the sky."""
    parts, labels = [], []

    def add(p, c):
        parts.append(p)
        labels.append(np.full(len(p), c))

    g = np.column_stack([rng.uniform(-60, 60, (30000, 2)), rng.normal(0, 0.02, 30000)])
    add(g, 2)
    for tx in (-40.0, 40.0):  # towers: 4 legs converging + arms at 25 m
        h = rng.uniform(0, 30, 1500)
        half = 4.0 * (1 - h / 35)
        sx, sy = rng.choice([-1, 1], 1500), rng.choice([-1, 1], 1500)
        add(np.column_stack([tx + sx * half, sy * half, h]), 15)
        arm = np.column_stack([np.full(200, tx), rng.uniform(-8, 8, 200), np.full(200, 25.0)])
        add(arm, 15)
    s = np.linspace(-40, 40, 600)
    for y in (-6.0, 6.0):
        add(np.column_stack([s, np.full_like(s, y), 25 - 0.004 * (1600 - s ** 2)]), 14)
    crown = rng.normal(0, 1.0, (3000, 3)) * [2.0, 2.0, 1.5] + [0, 0, 8]  # kept below the line
    add(crown, 5)
    roof = np.column_stack([rng.uniform(-25, -15, (3000, 2)) + [0, 45], np.full(3000, 8.0)])
    walls = np.column_stack([np.full(600, -25.0), rng.uniform(20, 30, 600), rng.uniform(0.5, 8, 600)])
    add(np.concatenate([roof, walls]), 6)
    add(np.column_stack([np.full(100, 30.0), np.full(100, 30.0), np.linspace(0.5, 9, 100)]), 1)
    add(np.array([[0.0, 50.0, 60.0]]), 7)
    xyz = np.concatenate(parts)
    return xyz, np.concatenate(labels)


def test_classes_of_a_synthetic_corridor():
    rng = np.random.default_rng(0)
    xyz, truth = _scene(rng)
    ground = truth == 2
    hag = xyz[:, 2].astype(np.float32)
    res = classify_obstacles(xyz, ground, hag, cfg=CFG.obstacles)
    c = res.classes
    legs = np.array([(tx, sy * 4.0) for tx in (-44.0, -36.0, 36.0, 44.0) for sy in (-1, 1)])
    leg_dist = np.linalg.norm(xyz[:, None, :2] - legs[None], axis=2).min(axis=1)
    assert (c[ground & (leg_dist > 1.5)] == 2).mean() > 0.995  # only the legs' own ground
    assert (c[ground & (leg_dist < 0.5)] == 15).mean() > 0.7  # tower legs stand on the ground
    assert (c[truth == 14] == 14).mean() > 0.8  # the ends at the arms join the towers
    assert (c[truth == 15] == 15).mean() > 0.8
    assert (c[truth == 5] == 14).mean() < 0.01 and (c[truth == 5] == 5).mean() > 0.8
    assert (c[truth == 6] == 6).mean() > 0.7  # walls apart from the roof stay unclassified
    assert (c[truth == 1] == 1).mean() > 0.9
    assert c[truth == 7][0] == 7
    towers = [o for o in res.objects if o.cls == 15]
    assert len([o for o in towers if o.height_above_ground > 25]) == 2
    wires = [o for o in res.objects if o.cls == 14]
    assert wires and max(o.clearance for o in wires) > 15


def test_vegetation_bands_and_degenerate_inputs():
    xyz = np.array([[0, 0, 0.3], [0.5, 0, 1.0], [1, 0, 3.0], [1.2, 0, 2.9]], float)
    res = classify_obstacles(xyz, np.zeros(4, bool), xyz[:, 2].astype(np.float32),
                             cfg=CFG.obstacles)
    assert res.classes[0] == 3 and res.classes[1] == 4 and res.classes[2] == 5
    empty = classify_obstacles(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, np.float32),
                               cfg=CFG.obstacles)
    assert empty.classes.shape == (0,) and empty.objects == ()
    ground = classify_obstacles(np.zeros((5, 3)), np.ones(5, bool), np.zeros(5, np.float32),
                                cfg=CFG.obstacles)
    assert (ground.classes == 2).all()
    one = classify_obstacles(np.array([[0.0, 0, 5]]), np.zeros(1, bool),
                             np.array([5.0], np.float32), cfg=CFG.obstacles)
    assert one.classes[0] == 7  # alone: noise


def test_clearance_grid_by_hand():
    xyz = np.array([[0.5, 0.5, 0], [1.5, 0.5, 10.0], [1.6, 0.6, 25.0], [2.5, 2.5, 0.0]])
    classes = np.array([2, 5, 14, 7], np.uint8)
    hag = np.array([0.0, 10.0, 25.0, 0.0], np.float32)
    from lidar_obstacles.config import replace

    cfg = replace(ObstacleDetectorConfig(), {"clearance.size": 5.0, "clearance.resolution": 1.0,
                                             "clearance.max_height": 50.0}).clearance
    cells, origin, res = clearance_grid(xyz, classes, hag, center_xy=np.array([2.5, 2.5]),
                                        cfg=cfg)
    assert res == 1.0 and tuple(origin) == (0.0, 0.0) and cells.shape == (5, 5)
    assert cells[0, 0] == 0  # ground only
    assert cells[0, 1] == 50  # the wire, 25 m of 50 -> 50 (the tree below it is lower)
    assert cells[2, 2] == 0  # noise is seen but is no obstacle
    assert cells[4, 4] == -1  # nothing fell there
