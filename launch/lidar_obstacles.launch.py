"""Start `obstacle_detector` and `dem_builder` (and, with `simplifier:=true`,
`cloud_simplifier`) with the package's config files.

    ros2 launch lidar_obstacles lidar_obstacles.launch.py points:=/lidar/points odom:=/odom \
        namespace:=uav1
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("lidar_obstacles")
    points = LaunchConfiguration("points")
    odom = LaunchConfiguration("odom")
    namespace = LaunchConfiguration("namespace")
    remaps = [("points", points), ("odom", odom)]
    return LaunchDescription([
        DeclareLaunchArgument("points", default_value="points",
                              description="PointCloud2 input topic"),
        DeclareLaunchArgument("odom", default_value="odom",
                              description="nav_msgs/Odometry of the vehicle"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the nodes, e.g. uav1"),
        DeclareLaunchArgument("simplifier", default_value="false",
                              description="also start cloud_simplifier (points_simplified)"),
        Node(package="lidar_obstacles", executable="obstacle_detector", namespace=namespace,
             parameters=[os.path.join(share, "config", "obstacle_detector.yaml")],
             remappings=remaps, output="screen"),
        Node(package="lidar_obstacles", executable="dem_builder", namespace=namespace,
             parameters=[os.path.join(share, "config", "dem_builder.yaml")],
             remappings=remaps, output="screen"),
        Node(package="lidar_obstacles", executable="cloud_simplifier", namespace=namespace,
             parameters=[os.path.join(share, "config", "cloud_simplifier.yaml")],
             remappings=remaps, output="screen",
             condition=IfCondition(LaunchConfiguration("simplifier"))),
    ])
