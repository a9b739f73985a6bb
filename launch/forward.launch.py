"""ros2 launch uw_sil forward.launch.py [sim_params:=fit.yaml] [bag:=trial.mcap] [method:=sil|dcp|udcp]
                                        [b_from_frame:=false] [rate:=1.0] [loop:=false] [keep_running:=false]
                                        [start_paused:=false] [image_transport:=raw|compressed]
                                        [pose_source:=topic|markers] [camera_info_file:=camera.yaml]

The forward half: sim_camera renders the panel at each pose with the fitted parameters (sim_params) and
the enhancer publishes camera/image_enhanced, the real frames dehazed with the synced simulated depth
(and bag_play replays a field trial when a bag is given; the launch then ends after the last frame, unless
keep_running:=true or loop:=true); a node that fails ends it with its reason (exit status 1).
`ros2 launch uw_sil forward.launch.py --show-args` lists the arguments. The graph is described in
uw_sil.nodes.graph and also started by `uw-sil launch forward`.
"""
from uw_sil.nodes.launchgen import generate


def generate_launch_description():
    return generate("forward")
