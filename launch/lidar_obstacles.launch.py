"""Start `obstacle_detector` and `dem_builder` (and, with `simplifier:=true`,
`cloud_simplifier`) with the package's config files.

    ros2 launch lidar_obstacles lidar_obstacles.launch.py points:=/lidar/points odom:=/odom \
        namespace:=uav1 large_data:=true

Arguments: points, odom (the input topics), namespace, simplifier, use_sim_time (for bags
played with --clock), detector_params / dem_params / simplifier_params (params files in
place of the shipped ones; their sections must reach the nodes under the namespace:
`/**/obstacle_detector`, as the shipped files are keyed), log_level, and large_data (Fast
DDS's shipped large-data profile for the nodes: clouds over its default 512 kB
shared-memory segment go by UDP otherwise; the clouds' publisher needs it too).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("lidar_obstacles")
    config = os.path.join(share, "config")
    remaps = [("points", LaunchConfiguration("points")), ("odom", LaunchConfiguration("odom"))]
    use_sim_time = {"use_sim_time": LaunchConfiguration("use_sim_time")}
    log_level = ["--log-level", LaunchConfiguration("log_level")]

    def node(executable, params_argument, **kwargs):
        return Node(package="lidar_obstacles", executable=executable,
                    namespace=LaunchConfiguration("namespace"),
                    parameters=[LaunchConfiguration(params_argument), use_sim_time],
                    remappings=remaps, ros_arguments=log_level, output="screen", **kwargs)

    arguments = [
        ("points", "points", "PointCloud2 input topic"),
        ("odom", "odom", "nav_msgs/Odometry of the vehicle"),
        ("namespace", "", "namespace of the nodes, e.g. uav1"),
        ("simplifier", "false", "also start cloud_simplifier (points_simplified)"),
        ("use_sim_time", "false", "take the time from /clock (a bag played with --clock)"),
        ("detector_params", os.path.join(config, "obstacle_detector.yaml"),
         "params file of obstacle_detector"),
        ("dem_params", os.path.join(config, "dem_builder.yaml"), "params file of dem_builder"),
        ("simplifier_params", os.path.join(config, "cloud_simplifier.yaml"),
         "params file of cloud_simplifier"),
        ("log_level", "info", "debug, info, warn, error or fatal"),
        ("large_data", "false", "run the nodes with the shipped Fast DDS large-data profile "
                                "(config/fastdds_large_data.xml)"),
    ]
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default, description=description)
          for name, default, description in arguments),
        SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE",
                               os.path.join(config, "fastdds_large_data.xml"),
                               condition=IfCondition(LaunchConfiguration("large_data"))),
        node("obstacle_detector", "detector_params"),
        node("dem_builder", "dem_params"),
        node("cloud_simplifier", "simplifier_params",
             condition=IfCondition(LaunchConfiguration("simplifier"))),
    ])
