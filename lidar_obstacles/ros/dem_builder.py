"""`dem_builder` node: ground (K-means or the detector's filter) into a rolling DEM grid,
published as `dem`, `dem_image` and `dem_info`, saved as GeoTIFF by the `save_dem` service."""
from __future__ import annotations

import os
import queue
import threading
import traceback

from nav_msgs.msg import MapMetaData
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from sensor_msgs.msg import Image, PointCloud2
from std_srvs.srv import Trigger

from lidar_obstacles.config import DemBuilderConfig
from lidar_obstacles.errors import LidarObstaclesError
from lidar_obstacles.ros.node_base import PipelineNode, create_output, run_node
from lidar_obstacles.ros.stages import DemStage, Pose


class DemBuilderNode(PipelineNode):
    config_cls = DemBuilderConfig
    services_wait = True  # save_dem waits for the worker thread (node_executor)
    remembers = "the DEM and its ground context"

    def __init__(self) -> None:
        super().__init__("dem_builder")
        self.stage = DemStage(self.cfg)
        self.pubs = {name: create_output(self, msg_type, name, depth=1, transient_local=True)
                     for name, msg_type in (("dem", PointCloud2), ("dem_image", Image),
                                            ("dem_info", MapMetaData))}
        self._dirty = False  # clouds since the last publish
        self._due = False  # the publish timer fired since the last publish
        self._timer = self.create_timer(1.0 / self.cfg.dem.publish_rate, self._publish_due)
        # save_dem calls for the worker thread to answer: (answered, answer) each
        self._saves: queue.SimpleQueue[tuple[threading.Event, list]] = queue.SimpleQueue()
        self.create_service(Trigger, "save_dem", self._save_dem,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.get_logger().info("ready")

    def _apply_config(self, cfg: DemBuilderConfig) -> None:
        old_rate = self.cfg.dem.publish_rate
        super()._apply_config(cfg)
        if cfg.dem.publish_rate != old_rate:  # (the timer is the executor's: changed here)
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(1.0 / cfg.dem.publish_rate, self._publish_due)

    def process_cloud(self, msg: PointCloud2, pose: Pose | None) -> tuple[int, int]:
        stats = self.stage.process(msg, pose)
        self.note_restart(stats["restart"])
        self._dirty = True
        # the cloud's finite points, and the ground points that went into the DEM
        return stats["points_in"], stats["points_out"]

    def _publish_due(self) -> None:
        """The publish timer, on the executor. The DEM is made on the worker thread: a big
        grid takes seconds (12 s at `dem.resolution` 0.05), and the executor waited as
        long, the parameter services, diagnostics and input with it."""
        self._due = True
        self.wake()

    def between_clouds(self) -> None:
        while not self._saves.empty():
            answered, answer = self._saves.get()
            answer.append(self._write_dem())
            answered.set()
        if not (self._due and self._dirty):
            return
        self._due = self._dirty = False
        for topic, out in self.stage.dem_outputs():
            self.pubs[topic].publish(out)
        if self.stage.coarse_warning and "coarse_dem" not in self._warned:
            self._warned.add("coarse_dem")
            self.get_logger().warning(self.stage.coarse_warning)

    def extra_diagnostics(self) -> dict[str, str]:
        """The DEM at its held-out check points, as of the last publish."""
        return self.stage.check_values()

    def _save_dem(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        """The service, on the executor's second thread (`services_wait`): the DEM is made
        and written on the worker thread, whose answer it waits for. Made on the executor,
        a big grid held it for seconds (0.66 s at `dem.resolution` 0.25, 12 s at 0.05), and
        with it the parameter services, the diagnostics and the odometry a waiting cloud
        needs."""
        answered = threading.Event()
        answer: list[tuple[bool, str]] = []  # (success, message), from the worker
        self._saves.put((answered, answer))
        self.wake()
        while not answered.wait(0.1):
            if self._stopping:
                response.success, response.message = False, "the node is stopping"
                return response
        response.success, response.message = answer[0]
        return response

    def _write_dem(self) -> tuple[bool, str]:
        """(success, message) of writing the current DEM to `export.path` (worker thread,
        `stage_lock` held)."""
        from lidar_obstacles.config import parse_crs
        from lidar_obstacles.io.geotiff import write_geotiff

        grid = self.stage.grid()
        # Named in full in the answer: a relative one is the node's working directory's, which
        # the caller (a launch file's) may not know.
        path = os.path.abspath(self.cfg.export.path)
        if grid.elevation.size == 0:
            return False, "no DEM yet: no ground received"
        try:
            epsg, wkt = parse_crs(self.cfg.export.crs)
            write_geotiff(path, grid, crs_epsg=epsg, crs_wkt=wkt)
        except LidarObstaclesError as exc:  # (its one line names the path or the parameter)
            return False, str(exc)
        except Exception as exc:  # noqa: BLE001 - an answer, not a node taken down
            self.get_logger().error(f"save_dem failed (a bug, please report it):\n"
                                    f"{traceback.format_exc()}")
            return False, f"{type(exc).__name__}: {exc}"
        return True, f"wrote {path}"


def main(args: list[str] | None = None) -> int:
    return run_node(DemBuilderNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
