"""ros2 launch uw_sil sil.launch.py [bag:=trial.mcap] [output_yaml:=fit.yaml] [frames:=3] [optimizer:=pso]
                                    [stride:=N] [max_iter:=N] [method:=sil] [b_from_frame:=false] [rate:=1.0]
                                    [loop:=false] [keep_running:=false]

Both halves of the paper: sim_camera, backward_fit (fits the first frames and re-parameterizes sim_camera)
and the enhancer (follows sim_camera's parameters and publishes camera/image_enhanced), plus bag_play when a
bag is given (the launch then ends when the fit is done, unless keep_running:=true). The same graph is
described in uw_sil.nodes.graph and started without ROS 2 launch by `uw-sil launch sil`.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from uw_sil.nodes.graph import share_file, sil_graph


def _nodes(context):
    get = lambda n: LaunchConfiguration(n).perform(context)  # noqa: E731
    flag = lambda n: get(n).lower() in ("true", "1")  # noqa: E731
    optional_int = lambda n: int(get(n)) if get(n) else None  # noqa: E731
    specs = sil_graph(sim_params=get("sim_params") or None, bag=get("bag") or None, output_yaml=get("output_yaml"),
                      frames=int(get("frames")), optimizer=get("optimizer"), rate=float(get("rate")),
                      loop=flag("loop"), max_iter=optional_int("max_iter"), stride=optional_int("stride"),
                      keep_running=flag("keep_running"), method=get("method"), b_from_frame=flag("b_from_frame"))
    return [Node(package="uw_sil", executable=s.executable, name=s.name, output="screen",
                 parameters=[*s.param_files, s.parameters], remappings=s.remappings, arguments=s.arguments,
                 on_exit=Shutdown() if s.required else None)
            for s in specs]


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("bag", default_value="", description="replay this field trial (mcap/sqlite3)"),
        DeclareLaunchArgument("sim_params", default_value="", description="sim_camera parameters YAML"),
        DeclareLaunchArgument("output_yaml", default_value="", description="write the fitted parameters here"),
        DeclareLaunchArgument("frames", default_value="3"),
        DeclareLaunchArgument("stride", default_value="", description="consider every n-th frame"),
        DeclareLaunchArgument("max_iter", default_value="", description="optimizer iterations"),
        DeclareLaunchArgument("optimizer", default_value="pso", choices=["pso", "cmaes"]),
        DeclareLaunchArgument("method", default_value="sil", choices=["sil", "dcp", "udcp"]),
        DeclareLaunchArgument("b_from_frame", default_value="false", choices=["true", "false"]),
        DeclareLaunchArgument("rate", default_value="1.0", description="bag replay rate"),
        DeclareLaunchArgument("loop", default_value="false", choices=["true", "false"]),
        DeclareLaunchArgument("keep_running", default_value="false", choices=["true", "false"],
                              description="with a bag: keep running after the fit"),
        SetEnvironmentVariable("FASTDDS_DEFAULT_PROFILES_FILE", str(share_file("config", "fastdds_shm.xml"))),
        OpaqueFunction(function=_nodes),
    ])
