"""rgb/hsv parameterizations, round trips, validation."""
import colorsys

import numpy as np
import pytest

from uw_sil.sim.params import (HSV_NAMES, ParamSpace, UnderwaterParams, hsv_to_rgb, hsv_to_rgb_params,
                           rgb_to_hsv, rgb_to_hsv_params)


def test_rgb_to_hsv_matches_colorsys():
    rng = np.random.default_rng(1)
    x = rng.random((200, 3))
    ours = rgb_to_hsv(x)
    ref = np.array([colorsys.rgb_to_hsv(*v) for v in x])
    np.testing.assert_allclose(ours, ref, atol=1e-12)
    back = hsv_to_rgb(ref)
    np.testing.assert_allclose(back, x, atol=1e-12)


def test_round_trip_parameters_including_grey_and_black():
    rng = np.random.default_rng(2)
    p = np.column_stack([rng.uniform(0, 0.8, (100, 3)), rng.random((100, 3)), rng.uniform(0, 0.5, 100)])
    p[0, 0:3] = 0.3          # grey attenuation: hue undefined
    p[1, 3:6] = 0.0          # black background
    np.testing.assert_allclose(hsv_to_rgb_params(rgb_to_hsv_params(p)), p, atol=1e-12)


def test_attenuation_value_keeps_units_and_hue_wraps():
    hsv = rgb_to_hsv_params([0.6, 0.15, 0.1, 0.0, 0.3, 0.4, 0.05])
    assert hsv[2] == pytest.approx(0.6)          # a_v = max attenuation, 1/m
    assert hsv[6] == 0.05
    shifted = hsv.copy()
    shifted[0] += 1.0                            # one full turn of hue: same colour
    np.testing.assert_allclose(hsv_to_rgb_params(shifted), hsv_to_rgb_params(hsv), atol=1e-12)


def test_underwater_params_object():
    p = UnderwaterParams(a=(0.3, 0.1, 0.05), b=(0.1, 0.2, 0.3), rho_f=0.02)
    assert UnderwaterParams.from_dict(p.as_dict()) == p
    q = UnderwaterParams.from_vector(p.to_hsv(), model="hsv")
    np.testing.assert_allclose(q.as_vector(), p.as_vector(), atol=1e-12)
    with pytest.raises(ValueError, match="b_g"):
        UnderwaterParams(b=(0.1, 1.2, 0.3))
    with pytest.raises(ValueError, match="missing parameters: rho_f"):
        UnderwaterParams.from_dict({k: 0.1 for k in ("a_r", "a_g", "a_b", "b_r", "b_g", "b_b")})
    with pytest.raises(ValueError, match="colour model"):
        UnderwaterParams.from_vector(np.zeros(7), model="lab")


def test_param_space_bounds_validation():
    s = ParamSpace("hsv")
    assert s.names == HSV_NAMES
    x = np.array([0.05, 0.7, 0.5, 0.55, 0.8, 0.4, 0.1])
    np.testing.assert_allclose(s.from_rgb(s.to_rgb(x)), x, atol=1e-12)
    lo, hi = s.lower.copy(), s.upper.copy()
    lo[3] = hi[3]
    with pytest.raises(ValueError, match="empty or inverted bounds for b_h"):
        ParamSpace("hsv", lo, hi)
    lo, hi = ParamSpace("rgb").lower.copy(), ParamSpace("rgb").upper.copy()
    hi[4] = 1.5
    with pytest.raises(ValueError, match="b_g"):
        ParamSpace("rgb", lo, hi)
    with pytest.raises(ValueError, match="7 values"):
        ParamSpace("rgb", lo[:6], hi)
    with pytest.raises(ValueError, match="not finite"):
        ParamSpace("rgb", lo, np.full(7, np.inf))
