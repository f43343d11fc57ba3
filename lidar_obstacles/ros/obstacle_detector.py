"""`obstacle_detector` node: ground, obstacles with classes, markers, the clearance grid and,
when `features.enabled`, the obstacles' feature points (`obstacle_edges`)."""
from __future__ import annotations

from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from lidar_obstacles.config import ObstacleDetectorConfig
from lidar_obstacles.ros.node_base import PipelineNode, create_output, run_node
from lidar_obstacles.ros.stages import DetectorStage


class ObstacleDetectorNode(PipelineNode):
    config_cls = ObstacleDetectorConfig
    out_key = "obstacles"
    remembers = "the ground context and the towers, wires and roofs seen"

    def __init__(self) -> None:
        super().__init__("obstacle_detector")
        self.stage = DetectorStage(self.cfg)
        self.pubs = {
            "ground": create_output(self, PointCloud2, "ground"),
            "obstacles": create_output(self, PointCloud2, "obstacles"),
            "obstacle_markers": create_output(self, MarkerArray, "obstacle_markers"),
            "clearance": create_output(self, OccupancyGrid, "clearance"),
            # Always there (`features.enabled` can be switched on at runtime); silent while off.
            "obstacle_edges": create_output(self, PointCloud2, "obstacle_edges"),
        }
        self.get_logger().info("ready")


def main(args: list[str] | None = None) -> int:
    return run_node(ObstacleDetectorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
