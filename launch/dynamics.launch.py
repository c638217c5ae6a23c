"""Start dynamics_node with a parameter file (a real ROS 2 Jazzy install).

    ros2 launch cdpr_dynamics dynamics.launch.py
    ros2 launch cdpr_dynamics dynamics.launch.py params_file:=/path/robot.yaml \
        pose_topic:=/controller/ee_pose wrench_topic:=/controller/ee_wrench

Arguments: ``params_file`` (default: the installed config/paper_cdpr.yaml), ``namespace``,
``pose_topic`` and ``wrench_topic`` (remappings of the node's ``pose`` and ``wrench``),
``log_level``. The shipped configs are keyed ``/**:``, so they apply in any ``namespace:=``;
a file of your own keyed ``cdpr_dynamics:`` matches only the root namespace (key it ``/**:``,
``/**/cdpr_dynamics:`` or ``/NAMESPACE/cdpr_dynamics:``); the node refuses a file with no
section for it, listing the keys it found.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory('cdpr_dynamics'), 'config',
                                  'paper_cdpr.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter YAML of the robot'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its topics'),
        DeclareLaunchArgument('pose_topic', default_value='pose',
                              description='end-effector PoseStamped input'),
        DeclareLaunchArgument('wrench_topic', default_value='wrench',
                              description='external WrenchStamped input'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='debug, info, warn, error or fatal'),
        Node(
            package='cdpr_dynamics',
            executable='dynamics_node',
            name='cdpr_dynamics',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file')],
            remappings=[('pose', LaunchConfiguration('pose_topic')),
                        ('wrench', LaunchConfiguration('wrench_topic'))],
            arguments=['--ros-args', '--log-level', LaunchConfiguration('log_level')],
            output='screen',
            emulate_tty=True,
        ),
    ])
