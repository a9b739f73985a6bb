"""Diagnosis plug-in of JPEG/MJPEG compression (:mod:`uw_sil.sim.effects.compression`).

Compression acts on 8x8 blocks of the recorded frame: the reduced frames of the θ refits (160-320 px wide)
average its blocks away, so it is judged at full resolution by a statistic instead, the *blockiness*: the
mean absolute luminance step across 8-pixel block boundaries over the mean step between neighbours inside
blocks (about 1 for an uncompressed frame; 1.08 at IJG quality 90, 1.47 at 50, measured on the effect).
The quality is chosen on the fit frames so that the simulation (current model at full resolution, the
camera noise estimated on the recording, then the JPEG round trip at 4:2:0) shows the recording's
blockiness; accepted when the held-out frames' blockiness distance shrinks beyond its bootstrap margin.
"""
from __future__ import annotations

import numpy as np

from ...sim.params import RGB_NAMES
from .base import Judge, Refit, bootstrap_se

#: Qualities tried (IJG scale): what cameras and image_transport use, from near-lossless down.
QUALITIES = (98.0, 95.0, 90.0, 85.0, 80.0, 70.0, 60.0, 50.0, 40.0, 30.0, 20.0, 10.0)


def blockiness(Y: np.ndarray, block: int = 8) -> float:
    """Mean absolute step across ``block``-pixel boundaries over the mean step inside blocks, of a
    luminance image (both directions; 1 = no block structure)."""
    Y = np.asarray(Y, np.float64)
    dx = np.abs(np.diff(Y, axis=1))
    dy = np.abs(np.diff(Y, axis=0))
    # diff index j is the step between columns j and j+1: a boundary where j + 1 is a multiple of block
    bx = (np.arange(dx.shape[1]) + 1) % block == 0
    by = (np.arange(dy.shape[0]) + 1) % block == 0
    across = np.concatenate([dx[:, bx].ravel(), dy[by, :].ravel()])
    inside = np.concatenate([dx[:, ~bx].ravel(), dy[~by, :].ravel()])
    eps = 1e-3                       # DN: a flat (black) frame has no steps at all and reads as 1
    return float((across.mean() + eps) / (inside.mean() + eps))


class CompressionJudge(Judge):
    effect = "compression"
    free = ("quality",)
    fixed = {"chroma": 1.0}
    res = "full"
    kind = "statistic"
    least_squares = False

    def refit(self, job, current, x_starts=None, parent=None):
        from ...sim.effects.compression import jpeg_roundtrip
        from ...sim.noise import NoiseField, water_noise_sigma
        from ...sim.optics import degrade
        from ..signatures import luminance

        p = np.clip(np.asarray(current.base, float), 0, None)
        p[3:6] = np.clip(p[3:6], 0, 1)

        def stats(frames, qualities):
            """per frame: the recording's blockiness, and the simulation's without compression and at each
            quality (noise estimated on the recording's water, a fixed realization per frame)."""
            real, sim = [], []
            for k, f in enumerate(frames):
                rr = f.render
                S = degrade(rr.rgb, rr.range, rr.depth, p, fog=job.fog) * 255.0
                sg = water_noise_sigma(f.image, ~np.isfinite(rr.range))
                S = S.astype(np.float32)
                NoiseField(S.shape, sg, seed=job.seed + 23 * k).apply(S)
                S = np.clip(S, 0, 255) / 255.0
                real.append(blockiness(luminance(f.image.astype(np.float32))))
                row = [blockiness(luminance(255.0 * S))]
                row += [blockiness(luminance(255.0 * jpeg_roundtrip(S, q, subsample=True))) for q in qualities]
                sim.append(row)
            return np.log(np.array(real)), np.log(np.array(sim))

        real_f, sim_f = stats(job.fit_f, QUALITIES)
        err = np.abs(sim_f[:, 1:] - real_f[:, None]).mean(axis=0)
        q = QUALITIES[int(np.argmin(err))]
        real_h, sim_h = stats(job.sel_f, (q,))
        e_base = np.abs(sim_h[:, 0] - real_h)
        e_cand = np.abs(sim_h[:, 1] - real_h)
        imp = e_base - e_cand
        stat = {"name": "blockiness (8x8 boundary steps over inner steps)", "real": float(np.exp(real_h).mean()),
                "base_sim": float(np.exp(sim_h[:, 0]).mean()), "candidate_sim": float(np.exp(sim_h[:, 1]).mean()),
                "improvement": float(imp.mean()), "margin": max(0.01, 2.0 * bootstrap_se(imp, seed=job.seed)),
                "per_frame_improvement": imp.tolist()}
        values = {"quality": float(q), **self.fixed}
        params = {"base": {k: float(v) for k, v in zip(RGB_NAMES, p)},
                  "effects": {self.effect: values}}
        return Refit(effect=self.effect, effects=(self.effect,), x=np.array([q]), params=params,
                     theta_fit=current.theta_fit, sel_pf=np.asarray(current.sel_pf), statistic=stat)

    def accept(self, r, current, margin, residual=None):
        st = r.statistic
        ok = st["improvement"] > st["margin"]
        return ok, st["improvement"] / st["margin"] if ok else 0.0, "statistic"

    def explain(self, e, gain, sig, camera=None):
        q = e.get("quality", 100)
        return (f"the recording was stored compressed (JPEG/MJPEG-like 8x8 blocks, chroma subsampled): about IJG "
                f"quality {q:.0f}, which costs {_psnr_note(q)}; the simulation's frames are compressed alike; {gain}")


def _psnr_note(q: float) -> str:
    return "little" if q >= 90 else ("visible block edges on smooth water" if q >= 50 else "strong blocking")


__all__ = ["CompressionJudge", "blockiness", "QUALITIES"]
