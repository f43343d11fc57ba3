"""The pipelines the nodes and `replay` share: one object per node, fed one cloud at a time.

`ObstacleDetector.process` runs ground filtering (with the rolling ground context of earlier
messages; `ground_step`), then obstacle classification and the clearance grid
(`obstacle_step`, which remembers the towers, wires and buildings it saw).
`DemPipeline.process` finds the ground (K-means or the detector's filter) and updates the
rolling DEM. Results are values; the only long-lived state is the ground context
(`StreamingGround`), the objects seen (`RecentObjects`) and the rolling DEM, each held by
one explicit object, so the halves can run in different processes (`replay`).
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from lidar_obstacles.config import DemBuilderConfig, DemConfig, ObstacleDetectorConfig
from lidar_obstacles.core.arrays import all_columns, column_max, column_min, points_xyz
from lidar_obstacles.core.classes import GROUND, NOISE

if TYPE_CHECKING:
    from lidar_obstacles.core.dem import DemGrid
    from lidar_obstacles.core.ground import GroundResult

# The rolling DEM is measured at the check points of the last this many messages.
CHECK_MESSAGES = 20


class RecentObjects:
    """What earlier messages recognised, kept for a while: rows whose first two columns are
    x, y (m), each with the stamp (s) of its message. Newest first, at most `size` rows
    (bounded memory on any flight), none older than `seconds`; `near` offers the rows
    within `radius` m of a box.

    With `voxel` (m), the rows' first three columns are x, y, z and a voxel of that fixed
    grid holds one row: the newest, its last column (a flag: a roof, not only what clings
    to one) the largest of theirs. A place seen again then costs no more rows: the
    simulated `mixed` flight's roofs were 31 684 rows in 1 406 voxels after 10 s, each
    roof seen again in every message that caught it."""

    def __init__(self, width: int, seconds: float, size: int, radius: float,
                 voxel: float | None = None) -> None:
        self.rows = np.zeros((0, width))
        self.stamps = np.zeros(0)
        self.seconds, self.size, self.radius, self.voxel = seconds, size, radius, voxel

    def near(self, lo: np.ndarray, hi: np.ndarray, stamp: float) -> np.ndarray:
        """(K, width) the rows within `radius` of the box lo..hi (2,) m, not too old."""
        xy = self.rows[:, :2]
        keep = (all_columns((xy >= lo - self.radius) & (xy <= hi + self.radius))
                & (self.stamps >= stamp - self.seconds))
        return self.rows[keep]

    def add(self, rows: np.ndarray, stamp: float) -> None:
        """Remember (R, width) rows of the message stamped `stamp` s; forget the old."""
        old = np.ones(len(self.rows), bool)
        if self.voxel is not None and len(rows):
            rows, old = self._merged(rows, self.voxel)
        all_rows = np.concatenate([rows, self.rows[old]])
        all_stamps = np.concatenate([np.full(len(rows), float(stamp)), self.stamps[old]])
        keep = np.flatnonzero(all_stamps >= stamp - self.seconds)[:self.size]
        self.rows, self.stamps = all_rows[keep], all_stamps[keep]

    def _merged(self, rows: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        """(R', width) the new rows one per voxel (edge `voxel` m), and (K,) bool: the old
        rows to keep (those in no voxel of the new ones, whose flags the new take)."""
        cells = np.floor(rows[:, :3] / voxel).astype(np.int64)
        lo, hi = column_min(cells), column_max(cells)
        span = hi - lo + 1  # numbered within the new rows' box: exact, however far out
        new_key = ((cells[:, 0] - lo[0]) * span[1] + cells[:, 1] - lo[1]) * span[2] \
            + cells[:, 2] - lo[2]
        key, first, group = np.unique(new_key, return_index=True, return_inverse=True)
        flag = np.full(len(key), -np.inf)
        np.maximum.at(flag, group, rows[:, -1])
        rows = rows[first]
        old = np.ones(len(self.rows), bool)
        # the old rows in the new rows' voxels: those in their box (with a voxel to spare
        # for the rounding), then by their voxels, as the new rows' were found
        near = np.flatnonzero(all_columns(
            (self.rows[:, :3] >= (lo - 1) * voxel) & (self.rows[:, :3] < (hi + 2) * voxel)))
        c = np.floor(self.rows[near, :3] / voxel).astype(np.int64)
        within = all_columns((c >= lo) & (c <= hi))
        inside, c = near[within], c[within] - lo
        if len(inside):
            old_key = (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]
            at = np.searchsorted(key, old_key)
            same = at < len(key)
            same[same] = key[at[same]] == old_key[same]
            np.maximum.at(flag, at[same], self.rows[inside[same], -1])
            old[inside[same]] = False
        rows[:, -1] = flag  # (rows[first] is a copy)
        return rows, old


# A strip that catches only a tower's legs still knows it: x, y, radius and height (m) of
# each tower.
def _tower_memory() -> RecentObjects:
    return RecentObjects(4, seconds=60.0, size=256, radius=50.0)


# A strip that catches a wire only in short pieces, or a tower but not its wires, still
# knows them: wire points 0.5 m apart (40 000: 20 km of conductor), offered out to SAG_FAR.
def _wire_memory() -> RecentObjects:
    from lidar_obstacles.core.obstacles import SAG_FAR

    return RecentObjects(4, seconds=30.0, size=40000, radius=SAG_FAR)


# A strip that catches a roof only in small pieces still knows the building, and so does a
# later pass over it: roof and wall points, one per 1 m voxel (100 000: ~10 ha of roof),
# offered as far as a piece may continue them.
def _building_memory(seconds: float) -> RecentObjects:
    from lidar_obstacles.core.obstacles import BUILDING_MEMORY_VOXEL

    return RecentObjects(4, seconds=seconds, size=100000, radius=5.0,
                         voxel=BUILDING_MEMORY_VOXEL)


# How long a message's obstacle candidates are kept for the shape context of a thin strip
# after it (a survey's 0.1 s slices: the strips before it, ~5 m each), and how many messages.
SHAPE_CONTEXT_SECONDS = 1.0
SHAPE_CONTEXT_MESSAGES = 20

# A cloud stamped more than this (s) before the newest one seen, or in another frame, starts
# what is remembered afresh (the ground context, the towers, wires and roofs seen, the DEM):
# the clock went back (a simulator reset, a bag played again, a driver's clock) or the
# frame changed, and what was remembered belongs elsewhere. Stamped "later", the ground
# context never aged out: a 6 m hill after a flat field kept 22 % of its ground as
# obstacles for good. Within it, a cloud is only late (and loses to what came after it).
RESTART_AFTER_S = 1.0


class Timeline:
    """Whether each cloud of a stream goes on with it or starts it over: its stamp went
    back by more than RESTART_AFTER_S, or its frame changed (as tf's buffer is cleared
    when ROS time jumps back)."""

    def __init__(self) -> None:
        self.newest: float | None = None  # s
        self.frame: str | None = None
        self.restarts = 0

    def restart(self, stamp: float, frame: str | None = None) -> str:
        """"" when the cloud stamped `stamp` s in `frame` (None: not known) goes on with
        the stream; else why it starts it over. Frames are named as tf2 names them: a
        leading '/' is the same frame (`/map` after `map` started over every time)."""
        why = ""
        if self.newest is not None and stamp < self.newest - RESTART_AFTER_S:
            why = (f"a cloud stamped {self.newest - stamp:.3f} s before the newest (the "
                   "clock went back)")
        elif (frame is not None and self.frame is not None
              and frame.lstrip("/") != self.frame.lstrip("/")):
            why = f"a cloud in frame '{frame}' after clouds in '{self.frame}'"
        if why:
            self.restarts += 1
            self.newest = stamp
        else:
            self.newest = stamp if self.newest is None else max(self.newest, stamp)
        self.frame = self.frame if frame is None else frame
        return why

    def saved(self) -> tuple[float | None, str | None, int]:
        """What `restore` puts back: the stream as it stood before a cloud."""
        return self.newest, self.frame, self.restarts

    def restore(self, saved: tuple[float | None, str | None, int]) -> None:
        """The stream as `saved` (a cloud refused after `restart` saw it changes nothing)."""
        self.newest, self.frame, self.restarts = saved


@dataclass(frozen=True)
class ClearanceGrid:
    """Occupancy-style grid: tallest obstacle above ground per cell scaled to 0-100, -1 unknown.

    cells: (rows, cols) int8, row = y index. origin: (2,) float64, x/y of the lower-left
    corner of cell (0, 0), metres. resolution: metres per cell.
    """

    cells: np.ndarray
    origin: np.ndarray
    resolution: float


@dataclass(frozen=True)
class GroundStep:
    """A cloud of N points after `ObstacleDetector.ground_step`: xyz (N, 3) float64 m,
    ground (N,) bool, height_above_ground (N,) float32 m (NaN where no surface), stamp s,
    vehicle_xyz (3,) m or None, timings s. Plain data: it may cross processes."""

    xyz: np.ndarray
    ground: np.ndarray
    height_above_ground: np.ndarray
    stamp: float
    vehicle_xyz: np.ndarray | None
    timings: dict[str, float]
    far: np.ndarray | None = None  # (N,) bool: stray points far from the cloud (noise)
    # The distinct points among those not far (None: all distinct): (U,) index of each
    # one's first occurrence and (M,) which of them each point is (:func:`distinct_points`).
    first: np.ndarray | None = None
    inverse: np.ndarray | None = None
    # Why this cloud started the stream over (Timeline; "" when it did not): the ground
    # context was forgotten before it, and the obstacle step forgets its memories too
    restart: str = ""


@dataclass(frozen=True)
class ObstacleResult:
    """What the obstacle detector found in one cloud of N points.

    ground: (N,) bool. classes: (N,) uint8 ASPRS code (2 ground). height_above_ground: (N,)
    float32 metres (NaN where no surface). object_id: (N,) int32, -1 outside objects.
    objects: the obstacle objects (boxes). clearance: the grid around the vehicle; for
    an empty cloud all unknown, and None when no position is known yet (no pose, no cloud
    before). timings: seconds per stage, plus "total".
    edges: (N,) bool, the obstacles' Gaussian-map feature points (crease, edge, corner),
    or None when `features.enabled` is off.
    """

    ground: np.ndarray
    classes: np.ndarray
    height_above_ground: np.ndarray
    object_id: np.ndarray
    objects: tuple
    clearance: ClearanceGrid | None
    timings: dict[str, float] = field(default_factory=dict)
    edges: np.ndarray | None = None


class StreamingGround:
    """The ground filter over a stream of clouds, with what it keeps between them: the
    rolling ground context and the random stream of the `ransac` method. The obstacle
    detector and the DEM's `detector` ground source both use one, so that the DEM
    `replay` builds from the detector's ground is the one `dem_builder` builds alone.

    cfg: any config with `tiling`, `ground`, `tin`, `ransac` and `context`."""

    def __init__(self, cfg: ObstacleDetectorConfig | DemBuilderConfig) -> None:
        from lidar_obstacles.core.context import GroundContext

        self.cfg = cfg
        self.context = GroundContext(cfg.context)
        self.rng = np.random.default_rng(cfg.ransac.seed)
        self.frame_jumps = 0  # clouds whose frame's height jumped (`context.frame_jump`)

    def reconfigure(self, cfg: ObstacleDetectorConfig | DemBuilderConfig) -> None:
        """New parameters; the context and the random stream are kept unless their own
        parameters changed."""
        from lidar_obstacles.core.context import GroundContext

        if cfg.context != self.cfg.context:
            self.context = GroundContext(cfg.context)
        if cfg.ransac.seed != self.cfg.ransac.seed:
            self.rng = np.random.default_rng(cfg.ransac.seed)
        self.cfg = cfg

    def restart(self) -> None:
        """Forget the ground context (the stream started over: :class:`Timeline`)."""
        from lidar_obstacles.core.context import GroundContext

        self.context = GroundContext(self.cfg.context)

    def saved(self) -> tuple:
        """What `restore` puts back: the context, the random stream and the count of frame
        jumps, as they stand before a cloud (its arrays are replaced, never written)."""
        return (self.context, self.context.saved(), self.rng.bit_generator.state,
                self.frame_jumps)

    def restore(self, saved: tuple) -> None:
        """The state `saved` (a cloud refused half-way changes nothing)."""
        self.context, arrays, rng_state, self.frame_jumps = saved
        self.context.restore(arrays)
        self.rng.bit_generator.state = rng_state

    def classify(self, xyz: np.ndarray, stamp: float
                 ) -> tuple[GroundResult, dict[str, float], np.ndarray | None,
                            tuple[np.ndarray, np.ndarray] | None]:
        """Ground of one cloud xyz (N >= 1, 3) float64 m, filtered with the context around
        it, which this cloud's ground then joins (stamp: seconds). Returns the result, the
        seconds spent reading the context, filtering and updating the context, the stray
        points far from the cloud in XY or z (:func:`far_points`; None when there are
        none): never ground, no height, and left out of the filter's raster, which one
        point kilometres away would have made gigabytes, and of the obstacles' shapes;
        and the distinct points among the others (:func:`distinct_points`; None when all
        are): a point given twice (merged tiles, a driver's repeat) is filtered once and
        both copies get its answer, as the obstacles do (`obstacle_step`). Counted twice,
        it had a neighbour at 0 m (never isolated noise), doubled the ground density
        the band narrows with, and made a single ground point per cell two."""
        from lidar_obstacles.core.arrays import distinct_points
        from lidar_obstacles.core.context import frame_jump
        from lidar_obstacles.core.ground import GroundResult, classify_ground, far_points

        cfg = self.cfg
        far: np.ndarray | None = far_points(xyz)
        full = xyz
        if far is not None and far.any():
            xyz = xyz[~far]
        else:
            far = None
        t0 = time.perf_counter()
        distinct = distinct_points(xyz)
        near = xyz
        if distinct is not None:
            xyz = xyz[distinct[0]]
        lo, hi = column_min(xyz[:, :2]), column_max(xyz[:, :2])
        context_xyz = self.context.points_near(lo, hi, stamp)
        if context_xyz is not None:  # the frame's height jumped: the context follows it
            jump = frame_jump(xyz, context_xyz, cfg.context.cell)
            if jump:
                context_xyz[:, 2] += jump
                self.context.shift(jump)
                self.frame_jumps += 1
        t1 = time.perf_counter()
        g = classify_ground(xyz, tiling=cfg.tiling, ground=cfg.ground, tin=cfg.tin,
                            ransac=cfg.ransac, context_xyz=context_xyz, rng=self.rng)
        t2 = time.perf_counter()
        self.context.update(xyz[g.ground], stamp, xyz[:, :2])
        timings = {"context": t1 - t0, "ground": t2 - t1,
                   "context_update": time.perf_counter() - t2}
        if distinct is not None:
            inverse = distinct[1]
            g = GroundResult(g.ground[inverse], g.height_above_ground[inverse], g.tiles,
                             g.splits, g.timings)
            xyz = near
        if far is not None:
            ground = np.zeros(len(full), bool)
            hag = np.full(len(full), np.nan, np.float32)
            ground[~far], hag[~far] = g.ground, g.height_above_ground
            g = GroundResult(ground, hag, g.tiles, g.splits, g.timings)
        return g, timings, far, distinct


class ObstacleDetector:
    """Ground, obstacles and clearance for a stream of clouds in a gravity-aligned frame."""

    def __init__(self, cfg: ObstacleDetectorConfig | None = None) -> None:
        self.cfg = cfg or ObstacleDetectorConfig()
        # One random stream per half (ground: the `ransac` method's tiles; obstacles: the
        # roofs' RANSAC), so that the halves may run in different processes.
        self.ground = StreamingGround(self.cfg)
        self._obstacle_rng = np.random.default_rng(self.cfg.ransac.seed)
        self._feature_rng = np.random.default_rng(self.cfg.features.seed)
        self.timeline = Timeline()
        self._forget()

    def _forget(self) -> None:
        """The obstacle half's memories, new: the towers, wires and roofs seen, and the
        obstacle candidates of the clouds just before."""
        self.towers, self.wires = _tower_memory(), _wire_memory()
        self.buildings = _building_memory(self.cfg.obstacles.building_memory)
        self.candidates: deque[tuple[float, np.ndarray]] = deque()  # (stamp s, (C, 3) m)
        # where the last clearance grid stood (2,) m: an empty cloud's, all unknown, too
        self._clearance_centre: np.ndarray | None = None

    def reconfigure(self, cfg: ObstacleDetectorConfig) -> None:
        """Take new parameters for the next message; the ground context is kept when its
        own parameters did not change."""
        self.ground.reconfigure(cfg)
        if cfg.ransac.seed != self.cfg.ransac.seed:
            self._obstacle_rng = np.random.default_rng(cfg.ransac.seed)
        if cfg.features.seed != self.cfg.features.seed:
            self._feature_rng = np.random.default_rng(cfg.features.seed)
        self.buildings.seconds = cfg.obstacles.building_memory
        self.cfg = cfg

    def process(self, xyz: np.ndarray, *, stamp: float = 0.0,
                vehicle_xyz: np.ndarray | None = None, frame: str | None = None
                ) -> ObstacleResult:
        """Classify one cloud: `ground_step`, then `obstacle_step`.

        xyz: (N, 3) float64 metres, z up. stamp: seconds (for the ground context's age).
        vehicle_xyz: (3,) the UAV position for the clearance grid (None: the cloud's centre).
        frame: the cloud's frame (None: not known); with the stamp, it tells when the
        stream starts over (:class:`Timeline`) and what was remembered is forgotten.
        """
        return self.obstacle_step(self.ground_step(xyz, stamp=stamp, vehicle_xyz=vehicle_xyz,
                                                   frame=frame))

    def ground_step(self, xyz: np.ndarray, *, stamp: float = 0.0,
                    vehicle_xyz: np.ndarray | None = None, frame: str | None = None
                    ) -> GroundStep:
        """The first half of `process`: ground and height above ground, with the ground
        context of earlier clouds, which this cloud's ground then joins. Its only state is
        the context, so `replay` can run the second half in another process, one cloud
        behind (a restart travels in the step). Arguments as :meth:`process`."""
        xyz = points_xyz(xyz, "obstacle detector")
        saved = self.timeline.saved(), self.ground.saved()
        restart = self.timeline.restart(stamp, frame)
        if restart:
            self.ground.restart()
        if len(xyz) == 0:
            return GroundStep(xyz, np.zeros(0, bool), np.zeros(0, np.float32), stamp,
                              vehicle_xyz, {"total": 0.0}, restart=restart)
        try:
            g, timings, far, distinct = self.ground.classify(xyz, stamp)
        except BaseException:
            # A cloud refused (`check_extent`: one that lies 1e9 m off) changes nothing:
            # its stamp or frame had started the stream over, forgetting the context, and
            # the next good cloud started it over again, uncounted
            self.timeline.restore(saved[0])
            self.ground.restore(saved[1])
            raise
        first, inverse = distinct if distinct is not None else (None, None)
        return GroundStep(xyz, g.ground, g.height_above_ground, stamp, vehicle_xyz, timings,
                          far, first, inverse, restart)

    def obstacle_step(self, step: GroundStep) -> ObstacleResult:
        """The second half of `process`: obstacle classes, objects and the clearance grid
        of a cloud whose ground `ground_step` found. Its only state is the towers, wires and
        buildings seen in earlier clouds."""
        from lidar_obstacles.core.obstacles import (ObstacleClasses, classify_obstacles,
                                                    clearance_grid, shape_context)

        cfg, xyz = self.cfg, step.xyz
        t3 = time.perf_counter()
        if step.restart:
            self._forget()
        if len(xyz) == 0:
            # (no return: high over the ground or water) nothing is known around the
            # vehicle now; the last grid, obstacles and all, stood for it until the next
            empty = np.zeros(0, bool)
            centre = (np.asarray(step.vehicle_xyz, float)[:2] if step.vehicle_xyz is not None
                      else self._clearance_centre)
            clearance = None
            if centre is not None:
                cells, origin, res = clearance_grid(np.zeros((0, 3)), np.zeros(0, np.uint8),
                                                    np.zeros(0, np.float32), centre_xy=centre,
                                                    cfg=cfg.clearance)
                clearance = ClearanceGrid(cells, np.asarray(origin, float), float(res))
            return ObstacleResult(empty, np.zeros(0, np.uint8), np.zeros(0, np.float32),
                                  np.zeros(0, np.int32), (), clearance, {"total": 0.0})
        near: slice | np.ndarray = slice(None)
        if step.far is not None or step.first is not None:
            near = np.arange(len(xyz)) if step.far is None else np.flatnonzero(~step.far)
            if step.first is not None:  # each distinct point once (StreamingGround.classify)
                near = near[step.first]
        lo, hi = column_min(xyz[near, :2]), column_max(xyz[near, :2])
        recent = [c for stamp, c in self.candidates
                  if step.stamp - SHAPE_CONTEXT_SECONDS <= stamp < step.stamp]
        context = shape_context(recent, xyz[near, :2], cfg.obstacles.feature_radius)
        ob = classify_obstacles(xyz[near], step.ground[near], step.height_above_ground[near],
                                cfg=cfg.obstacles, rng=self._obstacle_rng,
                                known_towers=self.towers.near(lo, hi, step.stamp),
                                known_wires=self.wires.near(lo, hi, step.stamp),
                                known_buildings=self.buildings.near(lo, hi, step.stamp),
                                context=context)
        if step.inverse is not None:  # the copies of a point get its answer
            ob = ObstacleClasses.repeat(ob, step.inverse)
        if step.far is not None:  # the stray points are noise, in no object
            ob = ObstacleClasses.expand(ob, ~step.far, NOISE)
        self.towers.add(ob.towers, step.stamp)
        self.wires.add(ob.wires, step.stamp)
        self.buildings.add(ob.buildings, step.stamp)
        self.candidates.append((step.stamp, ob.candidates))
        while (len(self.candidates) > SHAPE_CONTEXT_MESSAGES
               or self.candidates[0][0] < step.stamp - SHAPE_CONTEXT_SECONDS):
            self.candidates.popleft()
        t4 = time.perf_counter()
        centre = (np.asarray(step.vehicle_xyz, float)[:2] if step.vehicle_xyz is not None
                  else (lo + hi) / 2.0)
        self._clearance_centre = centre
        cells, origin, res = clearance_grid(xyz, ob.classes, step.height_above_ground,
                                            centre_xy=centre, cfg=cfg.clearance)
        t5 = time.perf_counter()
        timings = {**step.timings, "obstacles": t4 - t3, "clearance": t5 - t4}
        edges = None
        if cfg.features.enabled:
            if step.inverse is None:
                edges = self._obstacle_edges(xyz, ob.classes)
            else:  # found on the distinct points (the stray ones are noise: never edges)
                edges = np.zeros(len(xyz), bool)
                once = self._obstacle_edges(xyz[near], ob.classes[near])
                edges[slice(None) if step.far is None else ~step.far] = once[step.inverse]
            timings["features"] = time.perf_counter() - t5
        timings["total"] = sum(timings.values())
        return ObstacleResult(
            ground=ob.classes == GROUND, classes=ob.classes,
            height_above_ground=step.height_above_ground,
            object_id=ob.object_id, objects=ob.objects,
            clearance=ClearanceGrid(cells, np.asarray(origin, float), float(res)),
            timings=timings, edges=edges)

    def _obstacle_edges(self, xyz: np.ndarray, classes: np.ndarray) -> np.ndarray:
        """(N,) bool: the Gaussian-map feature points among the obstacle points of xyz
        (N, 3) m, found on the obstacles alone (not ground, not noise): a roof's edge
        against the ground beside it is the obstacle's outline, not a feature of it."""
        from lidar_obstacles.core.features import gaussian_map_features

        solid = (classes != GROUND) & (classes != NOISE)
        edges = np.zeros(len(xyz), bool)
        if solid.any():
            edges[solid] = gaussian_map_features(xyz[solid], cfg=self.cfg.features,
                                                 rng=self._feature_rng).feature
        return edges


# Points the wider band gives back stay out within this distance (m) of a ground patch the
# fixed band's pass dropped (ISPRS samp41: a roof taken for ground grew past `patch_area`).
_BLUNDER_MARGIN = 5.0
# A wider band by less than this (m) is not worth the second patch test: on dense scans
# (AHN, the simulator) the widening is a few cm and the DEM update stays ~7 ms cheaper.
_MIN_WIDENING = 0.05


def bare_earth(xyz: np.ndarray, height_above_ground: np.ndarray, cfg: DemConfig) -> np.ndarray:
    """(G,) bool: which of the detector's ground points xyz (G, 3) float64 metres the DEM
    takes as bare earth.

    Two tests, both on the ground points alone (what `replay` hands over): a point more
    than `dem.ground_band` m above the detector's surface (height_above_ground (G,) m,
    NaN counts as on it; band 0 keeps them all), widened by `dem.band_slope` x the point
    spacing x the surface's slope (:func:`lidar_obstacles.core.dem.band_allowance`), is
    low vegetation or a car inside the filter's acceptance band; the remaining points in
    small patches standing apart from the main ground (`dem.patch_area`,
    :func:`lidar_obstacles.core.dem.ground_blunders`) are tree crowns, roofs or low
    blunders the filter took for ground.
    """
    from scipy.spatial import cKDTree

    from lidar_obstacles.core.dem import band_allowance, ground_blunders

    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    finite = all_columns(np.isfinite(xyz))  # the DEM drops the rest
    hag = np.asarray(height_above_ground, float)
    height = np.nan_to_num(hag, nan=0.0)
    keep = ~(height > cfg.ground_band) if cfg.ground_band > 0 else np.ones(len(xyz), bool)

    def without_blunders(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = np.flatnonzero(mask & finite)
        dropped = np.zeros(len(xyz), bool)
        dropped[idx[ground_blunders(xyz[idx], max_area=cfg.patch_area, rise=cfg.patch_rise,
                                    sink=cfg.patch_sink)]] = True
        return mask & ~dropped, dropped

    keep, dropped = without_blunders(keep)
    if cfg.ground_band > 0 and cfg.band_slope > 0:
        widening = cfg.band_slope * band_allowance(xyz, hag)
        extra = np.flatnonzero(~keep & ~dropped & finite & (widening >= _MIN_WIDENING)
                               & (height <= cfg.ground_band + widening))
        if len(extra) and dropped.any():
            # not beside a patch the fixed band's pass dropped: a roof taken for ground
            # grows past `patch_area` with its points in the wider band, and then stays
            gap, _ = cKDTree(xyz[dropped, :2]).query(xyz[extra, :2],
                                                     distance_upper_bound=_BLUNDER_MARGIN)
            extra = extra[~np.isfinite(gap)]
        if len(extra):
            keep[extra] = True
            keep, _ = without_blunders(keep)
    return keep


def bare_earth_of(xyz: np.ndarray, ground: np.ndarray, height_above_ground: np.ndarray,
                  cfg: DemConfig) -> np.ndarray:
    """(N,) bool: :func:`bare_earth` of a whole cloud, xyz (N, 3) float64 metres, whose
    ground is ground (N,) bool, with height_above_ground (N,) m."""
    idx = np.flatnonzero(ground)
    out = np.zeros(len(xyz), bool)
    out[idx[bare_earth(xyz[idx], np.asarray(height_above_ground)[idx], cfg)]] = True
    return out


class DemPipeline:
    """Ground selection plus the rolling DEM, for the `dem_builder` node and `replay`."""

    def __init__(self, cfg: DemBuilderConfig | None = None, *, whole: bool = False) -> None:
        """whole: the DEM of everything, never a window (RollingDem's `whole`)."""
        from lidar_obstacles.core.dem import CheckPoints, RollingDem

        self.cfg = cfg or DemBuilderConfig()
        self.whole = whole
        self.dem = RollingDem(self.cfg, whole=whole)
        self._ground: StreamingGround | None = None  # the `detector` source's, on first use
        self._thin_rng = np.random.default_rng(self.cfg.thinning.seed)
        self.checks = CheckPoints(CHECK_MESSAGES * self.cfg.thinning.check_points)
        self.last_added = 0  # ground points the last cloud put into the DEM (diagnostics)
        self.timeline = Timeline()
        self.last_restart = ""  # why the last cloud started the DEM over ("": it did not)

    def _went_on(self, stamp: float, frame: str | None) -> None:
        """Start the DEM, its ground context and check points over when the cloud (stamp s,
        frame) starts the stream over (:class:`Timeline`): a DEM in one frame, or of one
        run of the clock, is not another's."""
        from lidar_obstacles.core.dem import CheckPoints, RollingDem

        self.last_restart = self.timeline.restart(stamp, frame)
        if self.last_restart:
            self.dem = RollingDem(self.cfg, whole=self.whole)
            if self._ground is not None:
                self._ground.restart()
            self.checks = CheckPoints(CHECK_MESSAGES * self.cfg.thinning.check_points)

    def reconfigure(self, cfg: DemBuilderConfig) -> None:
        """Apply a new config. A new grid (resolution, extent or max_cells) starts an empty
        DEM; otherwise the DEM kept applies the new settings from its next update. A new
        thinning seed or check-point count starts a fresh draw or check set."""
        from lidar_obstacles.core.dem import CheckPoints, RollingDem

        old = self.cfg
        grid_changed = (cfg.dem.resolution != old.dem.resolution
                        or cfg.dem.extent != old.dem.extent
                        or cfg.dem.max_cells != old.dem.max_cells)
        self.cfg = cfg
        if grid_changed:
            self.dem = RollingDem(cfg, whole=self.whole)
        else:
            self.dem.cfg = cfg  # interpolation settings apply from the next update
        if self._ground is not None:
            self._ground.reconfigure(cfg)
        if cfg.thinning.seed != old.thinning.seed:
            self._thin_rng = np.random.default_rng(cfg.thinning.seed)
        if cfg.thinning.check_points != old.thinning.check_points:
            self.checks = CheckPoints(CHECK_MESSAGES * cfg.thinning.check_points)

    def ground_of(self, xyz: np.ndarray, *, stamp: float,
                  intensity: np.ndarray | None) -> np.ndarray:
        """(N,) bool ground mask by the configured `dem.ground_source`. Never a stray point
        far from the cloud (:func:`far_points`): K-means would take one far below it for
        ground, and its grids would span the distance."""
        if self.cfg.dem.ground_source == "detector":
            if self._ground is None:
                self._ground = StreamingGround(self.cfg)
            g, _, _, _ = self._ground.classify(xyz, stamp)
            return bare_earth_of(xyz, g.ground, g.height_above_ground, self.cfg.dem)
        from lidar_obstacles.core.ground import check_extent, far_points
        from lidar_obstacles.core.kmeans import kmeans_ground

        near = ~far_points(xyz)
        if near.all():
            check_extent(xyz, self.cfg.ground.cell)
            return kmeans_ground(xyz, cfg=self.cfg.kmeans, intensity=intensity).ground
        check_extent(xyz[near], self.cfg.ground.cell)
        ground = np.zeros(len(xyz), bool)
        ground[near] = kmeans_ground(xyz[near], cfg=self.cfg.kmeans, intensity=None
                                     if intensity is None else intensity[near]).ground
        return ground

    def process(self, xyz: np.ndarray, *, stamp: float = 0.0,
                vehicle_xyz: np.ndarray | None = None,
                intensity: np.ndarray | None = None, frame: str | None = None
                ) -> dict[str, float]:
        """Add one cloud's ground to the rolling DEM. Returns timings in seconds.

        xyz: (N, 3) float64 metres, z up. stamp: seconds. vehicle_xyz: (3,) the UAV
        position, metres: a rolling window (`dem.extent` > 0) is centred on it (None: on
        the ground's mean). intensity: (N,) for the K-means ground source (None: geometry
        only). frame: the cloud's (None: not known); with the stamp it tells when the
        stream starts over, and the DEM with it (:class:`Timeline`)."""
        t0 = time.perf_counter()
        xyz = points_xyz(xyz, "DEM builder")
        saved = (self.timeline.saved(), self.dem, self.checks,
                 None if self._ground is None else self._ground.saved())
        self._went_on(stamp, frame)
        if len(xyz) == 0:
            self.last_added = 0
            return {"ground": 0.0, "update": 0.0, "total": 0.0}
        try:
            ground = self.ground_of(xyz, stamp=stamp, intensity=intensity)
        except BaseException:
            # a cloud refused changes nothing (as ObstacleDetector.ground_step): a stamp 0
            # or another frame had dropped the whole DEM, without a word
            self.timeline.restore(saved[0])
            self.dem, self.checks = saved[1], saved[2]
            if saved[3] is not None and self._ground is not None:
                self._ground.restore(saved[3])
            self.last_restart = ""
            raise
        t1 = time.perf_counter()
        timings = self._add(xyz[ground], stamp=stamp, vehicle_xyz=vehicle_xyz)
        return {"ground": t1 - t0, "update": timings["update"],
                "total": t1 - t0 + timings["update"]}

    def add_ground(self, ground_xyz: np.ndarray, *, stamp: float = 0.0,
                   vehicle_xyz: np.ndarray | None = None,
                   height_above_ground: np.ndarray | None = None,
                   frame: str | None = None) -> dict[str, float]:
        """Add ground points (G, 3) float64 metres found elsewhere (the obstacle detector's,
        in `replay`) to the rolling DEM; with their height above the detector's surface
        (G,) m, only the bare earth (:func:`bare_earth`). Then `thinning.check_points` of
        them are held out (`checks`, to measure the DEM: :meth:`check_accuracy`) and
        `thinning.keep` of the rest go into the DEM. Returns timings in seconds. frame:
        as :meth:`process`'s."""
        self._went_on(stamp, frame)
        return self._add(ground_xyz, stamp=stamp, vehicle_xyz=vehicle_xyz,
                         height_above_ground=height_above_ground)

    def _add(self, ground_xyz: np.ndarray, *, stamp: float,
             vehicle_xyz: np.ndarray | None = None,
             height_above_ground: np.ndarray | None = None) -> dict[str, float]:
        from lidar_obstacles.core.dem import thin

        t0 = time.perf_counter()
        ground_xyz = np.asarray(ground_xyz, np.float64).reshape(-1, 3)
        if height_above_ground is not None:
            ground_xyz = ground_xyz[bare_earth(ground_xyz, height_above_ground, self.cfg.dem)]
        if self.cfg.thinning.keep < 1.0 or self.cfg.thinning.check_points > 0:
            thinned = thin(ground_xyz, cfg=self.cfg.thinning, rng=self._thin_rng)
            self.checks.add(ground_xyz[thinned.check])
            ground_xyz = ground_xyz[thinned.keep]
        vehicle_xy = None if vehicle_xyz is None else np.asarray(vehicle_xyz, float)[:2]
        self.dem.update(ground_xyz, vehicle_xy, stamp)
        self.last_added = len(ground_xyz)
        t1 = time.perf_counter()
        return {"ground": 0.0, "update": t1 - t0, "total": t1 - t0}

    def check_accuracy(self, grid: DemGrid | None = None) -> dict[str, float | int | None]:
        """`grid` (default: a snapshot of the current DEM) at the held-out check points:
        check_rmse_m, check_r2, check_n."""
        return self.checks.accuracy(self.dem.snapshot() if grid is None else grid)
