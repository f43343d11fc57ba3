"""`cloud_simplifier` node: K-means++ simplification on normals of every cloud, published
as `points_simplified` (the kept points with all their fields)."""
from __future__ import annotations

from sensor_msgs.msg import PointCloud2

from lidar_obstacles.config import CloudSimplifierConfig
from lidar_obstacles.ros.node_base import PipelineNode, create_output, run_node
from lidar_obstacles.ros.stages import SimplifierStage


class CloudSimplifierNode(PipelineNode):
    config_cls = CloudSimplifierConfig

    def __init__(self) -> None:
        super().__init__("cloud_simplifier")
        self.stage = SimplifierStage(self.cfg)
        self.pubs = {"points_simplified": create_output(self, PointCloud2, "points_simplified")}
        self.get_logger().info("ready")


def main(args: list[str] | None = None) -> int:
    return run_node(CloudSimplifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
