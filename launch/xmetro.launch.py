"""Launch ``xmetro_node`` (colcon route): ``ros2 launch xmetro_ros xmetro.launch.py [arg:=value ...]``.

Arguments:
    namespace       namespace of the node ('' = none); its ``~/`` topics and services move with it.
    node_name       node name (default ``xmetro_node``); the params file is keyed ``/**`` so it applies to any name.
    params_file     ROS params file (default: the installed ``share/xmetro_ros/config/xmetro.yaml``).
    scan_topic      where the clouds come from (remaps the node's ``scan``; default ``scan``).
    settings_topic  where the scanner settings come from (remaps ``scanner_settings``; default ``scanner_settings``).
    log_level       ROS log level of the node (default ``info``).

Only the plain node is launched; the node's own behaviour (QoS, DDS environment) is what ``xmetro_node`` does.
Not run in this project's tests: the ``launch``/``launch_ros`` packages are not available as wheels here (the test
suite imports this file when they are, and byte-compiles it otherwise).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "xmetro_ros"


def generate_launch_description() -> LaunchDescription:
    default_params = PathJoinSubstitution([FindPackageShare(PACKAGE), "config", "xmetro.yaml"])
    args = [
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node"),
        DeclareLaunchArgument("node_name", default_value="xmetro_node", description="node name"),
        DeclareLaunchArgument("params_file", default_value=default_params, description="ROS params file"),
        DeclareLaunchArgument("scan_topic", default_value="scan", description="input clouds (remaps scan)"),
        DeclareLaunchArgument("settings_topic", default_value="scanner_settings",
                              description="input scanner settings (remaps scanner_settings)"),
        DeclareLaunchArgument("log_level", default_value="info", description="ROS log level"),
    ]
    node = Node(
        package=PACKAGE,
        executable="xmetro_node",
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file")],
        remappings=[("scan", LaunchConfiguration("scan_topic")),
                    ("scanner_settings", LaunchConfiguration("settings_topic"))],
        arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
        output="screen",
        emulate_tty=True,
    )
    return LaunchDescription([*args, node])
