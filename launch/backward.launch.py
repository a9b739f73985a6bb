"""ros2 launch uw_sil backward.launch.py [bag:=trial.mcap] [output_yaml:=fit.yaml] [frames:=3] [optimizer:=pso]
                                         [stride:=N] [max_iter:=N] [rate:=1.0] [loop:=false] [keep_running:=false]
                                         [start_paused:=false] [sim_params:=sim_camera.yaml]
                                         [diagnose:=false] [diagnose_frames:=8] [diagnose_max_effects:=4]
                                         [diagnose_effects:=NAME,...] [output_json:=diagnosis.json]
                                         [image_transport:=raw|compressed] [pose_source:=topic|markers]
                                         [camera_info_file:=camera.yaml]

Starts sim_camera and backward_fit (and bag_play when a bag is given): at dive start the first frames
are fitted and the simulated camera is re-parameterized through its parameter services. With a bag the
launch ends once the fit is done (backward_fit is required), unless keep_running:=true; a node that
fails ends it with its reason (exit status 1). `ros2 launch uw_sil backward.launch.py --show-args` lists
the arguments. The graph is described in uw_sil.nodes.graph and also started by `uw-sil launch backward`.

With diagnose:=true backward_fit diagnoses instead of fitting (the physics the simulation lacks, as `uw-sil
diagnose`): the result on /diagnostics and /backward_fit/diagnosis, the extended model sent to sim_camera.
image_transport:=compressed reads camera/image_raw/compressed; pose_source:=markers adds panel_pose, which
publishes the pose from the panel's markers on panel/pose; camera_info_file replaces camera/camera_info.
"""
from uw_sil.nodes.launchgen import generate


def generate_launch_description():
    return generate("backward")
