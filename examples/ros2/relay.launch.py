"""Launch `gcdtrav relay --ros` on a robot with a ROS 2 workspace (docs/ros2.md):

    source /opt/ros/jazzy/setup.bash          # the robot's own rclpy, on its own RMW (Fast DDS, Cyclone, ...)
    pip install gcdtrav                        # the base install: no torch
    ros2 launch examples/ros2/relay.launch.py offboard:=tcp/192.168.1.20:7447

The relay is a console script, not a ROS package: launch_ros runs the executable found on PATH (no
``package``) and adds the node name, namespace, parameters and remappings as ``--ros-args``.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    offboard = LaunchConfiguration("offboard")
    return LaunchDescription(
        [
            DeclareLaunchArgument("offboard", default_value="tcp/127.0.0.1:7447", description="the service's zenoh"),
            DeclareLaunchArgument("use_sim_time", default_value="false"),
            Node(
                executable="gcdtrav",
                arguments=["relay", "--ros", "-e", offboard],
                name="gcdtrav_relay",
                namespace="r1",  # relative topics below resolve under /r1
                output="screen",
                parameters=[
                    {
                        "camera": ["front/image_raw", "rear/image_raw/compressed"],
                        "source": ["r1/front", "r1/rear"],
                        # the service's grid takes the front camera's intrinsics from this key ('': none)
                        "camera_info_key": ["robot/r1/front/camera_info", ""],
                        "odometry_topic": "odom",
                        "odometry_key": "robot/r1/pose",
                        "use_sim_time": LaunchConfiguration("use_sim_time"),
                    }
                ],
                # the driver publishes elsewhere: remap instead of editing the parameters
                remappings=[("front/image_raw", "/front_camera/color/image_raw")],
            ),
        ]
    )
