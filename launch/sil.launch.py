"""ros2 launch uw_sil sil.launch.py [bag:=trial.mcap] [output_yaml:=fit.yaml] [frames:=3] [optimizer:=pso]
                                    [stride:=N] [max_iter:=N] [method:=sil] [b_from_frame:=false] [rate:=1.0]
                                    [loop:=false] [keep_running:=false] [start_paused:=false]
                                    [sim_params:=sim_camera.yaml] [diagnose:=false] [diagnose_frames:=8]
                                    [diagnose_max_effects:=4] [diagnose_effects:=NAME,...]
                                    [output_json:=diagnosis.json] [image_transport:=raw|compressed]
                                    [pose_source:=topic|markers] [camera_info_file:=camera.yaml]

Both halves of the paper: sim_camera, backward_fit (fits the first frames and re-parameterizes sim_camera)
and the enhancer (follows sim_camera's parameters and publishes camera/image_enhanced), plus bag_play when a
bag is given (the launch then ends when the fit is done, unless keep_running:=true); a node that fails ends
it with its reason (exit status 1). `ros2 launch uw_sil sil.launch.py --show-args` lists the arguments. The
graph is described in uw_sil.nodes.graph and also started by `uw-sil launch sil`. With diagnose:=true the
backward half diagnoses (see backward.launch.py) and the enhancer restores with the extended model.
"""
from uw_sil.nodes.launchgen import generate


def generate_launch_description():
    return generate("sil")
