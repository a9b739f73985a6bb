"""ros2 launch uw_sil forward.launch.py [sim_params:=fit.yaml] [bag:=trial.mcap] [method:=sil|dcp|udcp]
                                        [b_from_frame:=false] [rate:=1.0] [loop:=false] [keep_running:=false]

The forward half: sim_camera renders the panel at each pose with the fitted parameters (sim_params) and
the enhancer publishes camera/image_enhanced, the real frames dehazed with the synced simulated depth
(and bag_play replays a field trial when a bag is given; the launch then ends after the last frame, unless
keep_running:=true or loop:=true). The same graph is described in uw_sil.nodes.graph and started without
ROS 2 launch by `uw-sil launch forward`.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from uw_sil.nodes.graph import forward_graph, share_file


def _nodes(context):
    get = lambda n: LaunchConfiguration(n).perform(context)  # noqa: E731
    flag = lambda n: get(n).lower() in ("true", "1")  # noqa: E731
    specs = forward_graph(sim_params=get("sim_params") or None, bag=get("bag") or None, rate=float(get("rate")),
                          loop=flag("loop"), keep_running=flag("keep_running"), method=get("method"),
                          b_from_frame=flag("b_from_frame"))
    return [Node(package="uw_sil", executable=s.executable, name=s.name, output="screen",
                 parameters=[*s.param_files, s.parameters], remappings=s.remappings, arguments=s.arguments,
                 on_exit=Shutdown() if s.required else None)
            for s in specs]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("bag", default_value="", description="replay this field trial (mcap/sqlite3)"),
        DeclareLaunchArgument("sim_params", default_value="", description="fitted parameters YAML for sim_camera"),
        DeclareLaunchArgument("method", default_value="sil", choices=["sil", "dcp", "udcp"]),
        DeclareLaunchArgument("b_from_frame", default_value="false", choices=["true", "false"],
                              description="re-estimate the background on every frame from its water"),
        DeclareLaunchArgument("rate", default_value="1.0", description="bag replay rate"),
        DeclareLaunchArgument("loop", default_value="false", choices=["true", "false"]),
        DeclareLaunchArgument("keep_running", default_value="false", choices=["true", "false"],
                              description="with a bag: keep running after its last frame"),
        # Fast DDS defaults lose large images between processes: shared memory + loopback UDP profile.
        SetEnvironmentVariable("FASTDDS_DEFAULT_PROFILES_FILE", str(share_file("config", "fastdds_shm.xml"))),
        OpaqueFunction(function=_nodes),
    ])
