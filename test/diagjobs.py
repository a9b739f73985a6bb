"""A refit job on a small own trial, for tests of one diagnosis plug-in without a whole diagnosis."""
import json

import numpy as np


def base_model_job(tmp_path, effects: dict, ls_factor: int, size=(320, 240), recorded=None) -> tuple:
    """An own trial (6 frames, seed 3, ``size``) with ``effects`` concealed, a refit job on it (the fit and held-out
    frames at full resolution, least squares at ``1 / ls_factor`` of it, no CMA-ES) and the current model there: the
    base model at the trial's true parameters, least squares' reference fitted. ``(truth, job, current)``.
    ``recorded``: a function of a frame's (H, W, 3) uint8 image applied to every frame after its noise (the own
    generator adds the camera noise last; a codec comes after it in a camera)."""
    from uw_sil.bags.synth import synthesize_trial, truth_path
    from uw_sil.fit.diagfit import EffectModel
    from uw_sil.fit.judges import JUDGES, Current, Job
    from uw_sil.fit.judges.base import current_ls
    from uw_sil.fit.residuals import load_frames, reduce_frame, split_frames
    from uw_sil.sim.camera import CameraModel

    bag = tmp_path / "t.mcap"
    synthesize_trial(bag, n_frames=6, seed=3, camera=CameraModel.from_fov(*size), effects=effects)
    truth = json.loads(truth_path(bag).read_text())
    fit_f, sel_f = split_frames(load_frames(bag, k=6))
    if recorded is not None:
        for f in fit_f + sel_f:
            f.image = recorded(f.image)
    R = {id(f): reduce_frame(f, 1) for f in fit_f + sel_f}
    R_ls = {id(f): reduce_frame(f, ls_factor) for f in fit_f + sel_f}
    job = Job(fit_f=fit_f, sel_f=sel_f, R_hi=R, R_lo=R, R_ls=R_ls, fog="exp2", seed=0, max_iter=0, popsize=12,
              patience=6, sigs={}, prox={}, judges=JUDGES)
    base = np.array([truth["params"][k] for k in ("a_r", "a_g", "a_b", "b_r", "b_g", "b_b", "rho_f")])
    model = EffectModel(job.reduced(fit_f), (), fog="exp2", seed=0)
    x = model.x0(base)
    cur = current_ls(job, Current(effects=(), values={}, base=base,
                                  theta_fit=float(job.frame_theta(model, fit_f, x).mean()),
                                  sel_pf=job.frame_theta(model, sel_f, x, seed_offset=50)[0], x=x, model=model))
    return truth, job, cur
