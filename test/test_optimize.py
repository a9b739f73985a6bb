"""Tests of uw_sil.fit.optimize: the batched PSO (pyswarm) / CMA-ES layer of the backward optimization."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from uw_sil.fit.optimize import (
    PSO_PAPER_SETTINGS,
    OptimResult,
    StopOptimization,
    convergence_iteration,
    optimize,
    validate_bounds,
)

# A 7-D box with unequal ranges (like the simulator's parameters) and a known maximum C.
LO = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
HI = np.array([2.0, 2.0, 2.0, 1.0, 1.0, 1.0, 0.5])
C = np.array([0.7, 1.1, 0.4, 0.3, 0.6, 0.8, 0.1])
NAMES = ("a_r", "a_g", "a_b", "b_r", "b_g", "b_b", "rho_f")


def bowl(X):
    """Smooth concave bowl, maximum 1 at C."""
    return 1.0 - np.mean(((X - C) / (HI - LO)) ** 2, axis=-1)


def peak(X):
    """Narrower Gaussian peak, maximum 1 at C."""
    return np.exp(-np.sum(((X - C) / (0.3 * (HI - LO))) ** 2, axis=-1))


def noisy(f, sd=0.002, seed=0):
    """Batched objective: ``f`` plus additive Gaussian noise from its own generator."""
    rng = np.random.default_rng(seed)

    def obj(X):
        assert X.ndim == 2 and X.shape[1] == 7
        return f(X) + sd * rng.standard_normal(X.shape[0])

    return obj


def pseudo_noise(X):
    """Deterministic function of x (so evaluation order and batching do not matter)."""
    return bowl(X) + 0.003 * np.sin(1000.0 * X @ np.arange(1.0, 8.0))


def check_consistency(r: OptimResult, batch=None):
    """Counts, histories and recorded evaluations agree with each other."""
    ev = r.evaluations
    assert r.n_evals == len(ev) == ev.x.shape[0] == ev.f.shape[0] == ev.iteration.shape[0]
    assert int(ev.batch_sizes.sum()) == r.n_evals
    assert len(r.history_best_f) == r.n_iters + 1 == len(ev.batch_sizes)
    assert r.history_best_x.shape == (r.n_iters + 1, 7)
    if batch is not None:
        assert np.all(ev.batch_sizes == batch)
    assert np.all((ev.x >= LO) & (ev.x <= HI))
    for k in range(r.n_iters + 1):  # history recomputed from the recorded evaluations
        upto = ev.iteration <= k
        j = int(np.argmax(ev.f[upto]))
        assert r.history_best_f[k] == ev.f[upto][j]
        np.testing.assert_array_equal(r.history_best_x[k], ev.x[upto][j])
    assert r.f_best == r.history_best_f[-1] == ev.f.max()
    np.testing.assert_array_equal(r.x_best, r.history_best_x[-1])
    assert r.converged_iter == convergence_iteration(r.history_best_f, r.tol)
    assert r.n_invalid == int(np.sum(ev.f == -np.inf))


# ---------------------------------------------------------------------------- convergence_iteration


def test_convergence_iteration_constructed():
    h = [0.1, 0.5, 0.8, 0.80005, 0.80008, 0.80009]
    assert convergence_iteration(h, tol=1e-4) == 2  # 0.80009 - 0.8 <= 1e-4
    assert convergence_iteration(h, tol=5e-5) == 3  # 0.80009 - 0.80005 <= 5e-5, 0.80009 - 0.8 is not
    assert convergence_iteration(h, tol=0.0) == 5
    assert convergence_iteration(h, tol=1.0) == 0
    # many small steps add up: each step is < tol but the total after index 1 is not
    assert convergence_iteration([0.0, 0.1, 0.15, 0.2, 0.25, 0.3], tol=0.06) == 4
    assert convergence_iteration([0.7] * 5, tol=1e-4) == 0
    assert convergence_iteration([-np.inf, -np.inf, 0.3, 0.6, 0.6], tol=1e-3) == 3
    assert convergence_iteration([-np.inf, -np.inf], tol=1e-3) == 0
    assert convergence_iteration([0.42], tol=1e-4) == 0


@pytest.mark.parametrize("h, tol, msg", [
    ([], 1e-4, "non-empty"),
    ([0.1, np.nan], 1e-4, "NaN"),
    ([0.1, np.inf], 1e-4, "NaN or \\+inf"),
    ([0.1, 0.3, 0.2], 1e-4, "decreases at index 2"),
    ([0.1, 0.2], -1.0, "tol"),
    ([0.1, 0.2], np.nan, "tol"),
])
def test_convergence_iteration_rejects(h, tol, msg):
    with pytest.raises(ValueError, match=msg):
        convergence_iteration(h, tol)


# ---------------------------------------------------------------------------- bounds validation


def test_validate_bounds_ok():
    lo, hi = validate_bounds([0, 1], (1, 2.5))
    assert lo.dtype == float and hi.tolist() == [1.0, 2.5]


@pytest.mark.parametrize("lower, upper, names, msg", [
    ([], [], None, "empty"),
    ([0, 0], [1], None, "2 entries but upper has 1"),
    ([[0, 0]], [[1, 1]], None, "1-D"),
    ([0, np.nan], [1, 1], None, "parameter 1: bounds must be finite"),
    ([0, 0], [1, np.inf], ["a", "b"], "parameter 1 \\('b'\\): bounds must be finite"),
    ([0, 0, 3], [1, 1, 3], ["a", "b", "c"], "parameter 2 \\('c'\\): empty bounds"),
    ([0, 2], [1, 1], ["x", "rho_f"], "parameter 1 \\('rho_f'\\): inverted bounds"),
    ([0, 0], [1, 1], ["x"], "1 names for 2 parameters"),
    (["a", "b"], [1, 1], None, "numeric"),
])
def test_validate_bounds_rejects(lower, upper, names, msg):
    with pytest.raises(ValueError, match=msg):
        validate_bounds(lower, upper, names)


def test_optimize_validates_bounds_and_settings():
    obj = noisy(bowl)
    with pytest.raises(ValueError, match="parameter 6 \\('rho_f'\\): inverted"):
        optimize(obj, LO, np.r_[HI[:6], -1.0], names=NAMES)
    with pytest.raises(ValueError, match="unknown method"):
        optimize(obj, LO, HI, method="de")
    with pytest.raises(TypeError, match="unknown option"):
        optimize(obj, LO, HI, method="pso", sigma0=0.2)
    with pytest.raises(TypeError, match="unknown option"):
        optimize(obj, LO, HI, method="cmaes", minfunc=0.1)
    with pytest.raises(ValueError, match="PSO settings"):
        optimize(obj, LO, HI, method="cmaes", omega=0.4)
    with pytest.raises(ValueError, match="cma_options"):
        optimize(obj, LO, HI, method="cmaes", cma_options={"bounds": [0, 1]})
    with pytest.raises(ValueError, match="max_iter"):
        optimize(obj, LO, HI, max_iter=0)
    with pytest.raises(ValueError, match="swarm_size"):
        optimize(obj, LO, HI, swarm_size=1)
    with pytest.raises(ValueError, match="seed"):
        optimize(obj, LO, HI, seed=-1)
    with pytest.raises(ValueError, match="x0: parameter 0 \\('a_r'\\)"):
        optimize(obj, LO, HI, names=NAMES, x0=np.r_[2.5, C[1:]])
    with pytest.raises(ValueError, match="x0 must have shape"):
        optimize(obj, LO, HI, method="cmaes", x0=np.stack([C, C]))
    with pytest.raises(TypeError, match="callable"):
        optimize(None, LO, HI)


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_objective_output_is_checked(method):
    with pytest.raises(ValueError, match=r"shape \(\d+,\)"):
        optimize(lambda X: bowl(X)[:, None], LO, HI, method=method, seed=0)
    with pytest.raises(ValueError, match=r"shape \(\d+,\)"):
        optimize(lambda X: bowl(X)[:-1], LO, HI, method=method, seed=0)


# ---------------------------------------------------------------------------- finding the maximum


def test_paper_settings_constant():
    assert dict(PSO_PAPER_SETTINGS) == {"swarm_size": 20, "omega": 0.4, "phi_p": 0.3,
                                        "phi_g": 0.3, "max_iter": 100}
    with pytest.raises(TypeError):
        PSO_PAPER_SETTINGS["omega"] = 0.5


def test_pso_paper_finds_max_of_noisy_bowl():
    r = optimize(noisy(bowl, seed=1), LO, HI, method="pso", seed=0, names=NAMES)
    check_consistency(r, batch=20)
    assert r.settings["paper_settings"] and r.settings["swarm_size"] == 20
    assert r.stop_reason == "max_iter" and r.n_iters == 100 and r.n_evals == 2020
    assert bowl(r.x_best) > 0.95  # the paper's PSO converges early: coarse but in the right place
    assert abs(r.f_best - bowl(r.x_best)) < 0.01
    assert set(r.best_params) == set(NAMES)


def test_cmaes_finds_max_of_noisy_bowl():
    r = optimize(noisy(bowl, seed=1), LO, HI, method="cmaes", seed=0)
    check_consistency(r, batch=9)  # 4 + floor(3 ln 7)
    assert r.settings["swarm_size"] == 9 and r.settings["sigma0"] == 0.25
    assert r.stop_reason == "max_iter" and r.n_iters == 100 and r.n_evals == 909
    assert bowl(r.x_best) > 0.995


def test_cmaes_locates_noisy_peak():
    r = optimize(noisy(peak, seed=3), LO, HI, method="cmaes", seed=3)
    check_consistency(r)
    assert peak(r.x_best) > 0.99
    assert np.max(np.abs(r.x_best - C) / (HI - LO)) < 0.03


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_nan_region_does_not_poison(method):
    def obj(X):
        f = noisy(bowl, seed=5)(X)
        f[X[:, 0] > 1.4] = np.nan  # 30 % of a_r's range is degenerate
        f[X[:, 3] > 0.8] = -np.inf
        f[X[:, 5] < 0.05] = np.inf
        return f

    r = optimize(obj, LO, HI, method=method, seed=2)
    check_consistency(r)
    ev = r.evaluations
    invalid = (ev.x[:, 0] > 1.4) | (ev.x[:, 3] > 0.8) | (ev.x[:, 5] < 0.05)
    assert invalid.any() and r.n_invalid == int(invalid.sum())
    np.testing.assert_array_equal(ev.f == -np.inf, invalid)
    assert np.isfinite(r.f_best)
    assert bowl(r.x_best) > (0.95 if method == "pso" else 0.995)
    json.dumps(r.to_dict(), allow_nan=False)  # -inf recorded, still strict JSON


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_all_invalid_raises(method):
    with pytest.raises(RuntimeError, match="non-finite"):
        optimize(lambda X: np.full(len(X), np.nan), LO, HI, method=method, seed=0, max_iter=3)


# ---------------------------------------------------------------------------- pyswarm equivalence


def test_pso_is_pyswarm_step_for_step():
    """Batched driving of pyswarm's core == pyswarm.pso on the normalized box, same seed."""
    from pyswarm import pso

    calls = []

    def per_particle(u):
        calls.append(np.array(u))
        x = np.clip(LO + u * (HI - LO), LO, HI)
        return -float(pseudo_noise(x[None])[0])

    ref = pso(per_particle, np.zeros(7), np.ones(7), swarmsize=20, omega=0.4, phip=0.3, phig=0.3,
              maxiter=100, seed=11)
    r = optimize(pseudo_noise, LO, HI, method="pso", seed=11)
    check_consistency(r, batch=20)
    U = np.array(calls)
    np.testing.assert_array_equal(r.evaluations.x, np.clip(LO + U * (HI - LO), LO, HI))
    assert r.f_best == -ref.fun
    np.testing.assert_array_equal(r.x_best, np.clip(LO + ref.x * (HI - LO), LO, HI))
    # this run stops early on pyswarm's minstep/minfunc rule; pyswarm's counts are then one short
    assert r.stop_reason in ("minstep", "minfunc") and r.n_iters < 100
    assert ref.nit == r.n_iters - 1 and ref.nfev == r.n_evals - 20
    assert r.backend_info["pyswarm_nit"] == ref.nit


def test_pso_full_run_counts_match_pyswarm():
    r = optimize(noisy(bowl), LO, HI, method="pso", seed=4, max_iter=30)
    assert r.stop_reason == "max_iter"
    assert r.backend_info["pyswarm_nit"] == r.n_iters == 30
    assert r.backend_info["pyswarm_nfev"] == r.n_evals == 20 * 31


def test_pso_x0_seeds_first_particles():
    starts = np.stack([C, LO, HI])
    r = optimize(noisy(bowl), LO, HI, method="pso", seed=0, x0=starts, max_iter=2)
    np.testing.assert_allclose(r.evaluations.x[:3], starts, rtol=0, atol=1e-12)
    r1 = optimize(noisy(bowl), LO, HI, method="pso", seed=0, max_iter=2)
    np.testing.assert_array_equal(r.evaluations.x[3:20], r1.evaluations.x[3:20])


# ---------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_same_seed_same_run(method):
    np.random.seed(123)
    state = np.random.get_state()[1].copy()
    a = optimize(noisy(bowl, seed=9), LO, HI, method=method, seed=7, max_iter=20)
    b = optimize(noisy(bowl, seed=9), LO, HI, method=method, seed=7, max_iter=20)
    np.testing.assert_array_equal(np.random.get_state()[1], state)  # global RNG untouched
    np.testing.assert_array_equal(a.evaluations.x, b.evaluations.x)
    np.testing.assert_array_equal(a.evaluations.f, b.evaluations.f)
    assert a.history_best_f == b.history_best_f and a.seed == b.seed == 7
    d = optimize(noisy(bowl, seed=9), LO, HI, method=method, seed=8, max_iter=20)
    assert not np.array_equal(a.evaluations.x, d.evaluations.x)


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_objective_using_global_rng_does_not_change_the_search(method):
    def plain(X):
        return bowl(X)

    def draws_from_global_rng(X):
        np.random.standard_normal(5 * len(X))  # e.g. a renderer jittering with np.random
        return bowl(X)

    a = optimize(plain, LO, HI, method=method, seed=3, max_iter=15)
    b = optimize(draws_from_global_rng, LO, HI, method=method, seed=3, max_iter=15)
    np.testing.assert_array_equal(a.evaluations.x, b.evaluations.x)


def test_seed_none_is_recorded_and_replays():
    a = optimize(noisy(bowl, seed=2), LO, HI, method="cmaes", seed=None, max_iter=5)
    b = optimize(noisy(bowl, seed=2), LO, HI, method="cmaes", seed=a.seed, max_iter=5)
    np.testing.assert_array_equal(a.evaluations.x, b.evaluations.x)


# ---------------------------------------------------------------------------- target, callback, progress


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_target_stops_and_counts(method):
    n_calls = []

    def obj(X):
        n_calls.append(len(X))
        return bowl(X)

    r = optimize(obj, LO, HI, method=method, seed=1, target=0.97)
    check_consistency(r)
    assert r.stop_reason == "target" and r.f_best >= 0.97
    f = r.evaluations.f
    k = r.evals_to_target
    assert f[k - 1] >= 0.97 and np.all(f[: k - 1] < 0.97)
    assert r.evaluations.iteration[k - 1] == r.n_iters  # stopped right after that iteration
    assert sum(n_calls) == r.n_evals and len(n_calls) == r.n_iters + 1
    assert r.n_iters < 100
    unreachable = optimize(bowl, LO, HI, method=method, seed=1, target=1.5, max_iter=5)
    assert unreachable.evals_to_target is None and unreachable.stop_reason == "max_iter"


@pytest.mark.parametrize("method", ["pso", "cmaes"])
@pytest.mark.parametrize("how", ["return", "raise"])
def test_callback_stop(method, how, capfd):
    seen = []
    n_calls = []

    def obj(X):
        n_calls.append(len(X))
        return noisy(bowl)(X)

    def cb(iteration, best_x, best_f):
        seen.append((iteration, best_x.copy(), best_f))
        best_x[:] = -1.0  # a copy: must not corrupt the optimizer
        if iteration == 3:
            if how == "raise":
                raise StopOptimization
            return True
        return None

    r = optimize(obj, LO, HI, method=method, seed=0, callback=cb)
    check_consistency(r)
    assert r.stop_reason == "callback" and r.n_iters == 3 and len(n_calls) == 4
    assert [s[0] for s in seen] == [0, 1, 2, 3]
    assert [s[2] for s in seen] == r.history_best_f
    np.testing.assert_array_equal(np.array([s[1] for s in seen]), r.history_best_x)
    assert capfd.readouterr().err == ""  # stopping does not raise through pyswarm's Fortran


# the backends' own stopping rules, off to isolate the stop on convergence
OWN_RULES_OFF = {"cmaes": {"cma_options": {"tolfun": 0, "tolx": 0}}, "pso": {"minfunc": 0.0, "minstep": 0.0}}


@pytest.mark.parametrize("method", ["pso", "cmaes"])
@pytest.mark.parametrize("tol, patience", [(1e-3, 5), (1e-5, 10), (1e-6, 3)])
def test_stop_on_convergence_is_the_first_window_that_gained_at_most_tol(method, tol, patience, capfd):
    n_calls = []

    def obj(X):
        n_calls.append(len(X))
        return pseudo_noise(X)

    r = optimize(obj, LO, HI, method=method, seed=2, tol=tol, patience=patience, **OWN_RULES_OFF[method])
    check_consistency(r)
    h = np.array(r.history_best_f)
    gains = h[patience:] - h[:-patience]                 # gains over the windows ending at k = patience, ...
    stops = np.flatnonzero(gains <= tol)
    assert r.stop_reason == "converged" and r.n_iters == patience + stops[0] < 100
    assert len(n_calls) == r.n_iters + 1                 # no evaluation after the stop
    assert r.settings["patience"] == patience and r.to_dict()["patience"] == patience
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("method", ["pso", "cmaes"])
def test_no_stop_on_convergence_by_default_or_with_patience_0(method):
    for kw in ({}, {"patience": 0, "tol": 1.0}):
        r = optimize(bowl, LO, HI, method=method, seed=0, max_iter=12, **OWN_RULES_OFF[method], **kw)
        assert r.stop_reason == "max_iter" and r.n_iters == 12 and r.patience == 0
    paper = optimize(bowl, LO, HI, method="pso", seed=0, max_iter=100)
    assert paper.settings["paper_settings"] and not optimize(bowl, LO, HI, method="pso", seed=0, max_iter=100,
                                                             patience=5).settings["paper_settings"]


def test_convergence_options_are_checked():
    with pytest.raises(ValueError, match="patience"):
        optimize(bowl, LO, HI, patience=-1)
    with pytest.raises(ValueError, match="patience"):
        optimize(bowl, LO, HI, patience=2.5)


@pytest.mark.parametrize("method", ["pso", "cmaes"])
@pytest.mark.parametrize("where", ["callback", "objective"])
def test_keyboard_interrupt_propagates_and_leaves_no_state(method, where):
    calls = {"n": 0}

    def obj(X):
        calls["n"] += 1
        if where == "objective" and calls["n"] == 3:
            raise KeyboardInterrupt
        return noisy(bowl, seed=calls["n"])(X)

    def cb(iteration, best_x, best_f):
        if where == "callback" and iteration == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        optimize(obj, LO, HI, method=method, seed=0, callback=cb)
    # a later run is unaffected
    a = optimize(noisy(bowl), LO, HI, method=method, seed=0, max_iter=3)
    b = optimize(noisy(bowl), LO, HI, method=method, seed=0, max_iter=3)
    np.testing.assert_array_equal(a.evaluations.x, b.evaluations.x)


def test_progress_bar_on_stderr(capsys):
    optimize(noisy(bowl), LO, HI, method="pso", seed=0, max_iter=4, progress=True)
    err = capsys.readouterr().err
    assert "pso" in err and "best=" in err and "5/5" in err
    optimize(noisy(bowl), LO, HI, method="pso", seed=0, max_iter=4)
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------------------- result


def test_to_dict_is_json():
    r = optimize(noisy(bowl), LO, HI, method="cmaes", seed=0, max_iter=5, names=NAMES, target=2.0)
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert d["method"] == "cmaes" and d["n_evals"] == r.n_evals == len(d["evaluations"]["f"])
    assert d["names"] == list(NAMES) and d["best_params"]["rho_f"] == r.x_best[6]
    assert d["history_best_f"] == r.history_best_f and d["evals_to_target"] is None
    assert "evaluations" not in r.to_dict(include_evaluations=False)
    assert math.isclose(d["f_best"], r.f_best)


def test_cmaes_evaluates_x0_first_so_a_good_start_is_never_lost():
    lo, hi = np.zeros(3), np.ones(3)
    x0 = np.array([0.3, 0.6, 0.2])

    def f(X):
        return -np.sum((X - x0) ** 2, axis=1)

    res = optimize(f, lo, hi, method="cmaes", seed=4, max_iter=2, x0=x0, sigma0=0.3)
    first = res.evaluations.x[res.evaluations.iteration == 0]
    assert np.any(np.all(np.isclose(first, x0), axis=1))
    assert res.f_best == pytest.approx(0.0, abs=1e-12)


def test_cmaes_stops_when_its_step_has_collapsed():
    """min_step: the first generation after which the largest coordinate std (normalized box) is below it."""
    r = optimize(bowl, LO, HI, method="cmaes", seed=0, max_iter=200, min_step=1e-3, **OWN_RULES_OFF["cmaes"])
    check_consistency(r)
    steps = np.array(r.backend_info["step_history"])
    assert r.stop_reason == "step" and len(steps) == r.n_iters + 1
    assert steps[-1] < 1e-3 and np.all(steps[:-1] >= 1e-3)
    assert r.settings["min_step"] == 1e-3
    off = optimize(bowl, LO, HI, method="cmaes", seed=0, max_iter=30, **OWN_RULES_OFF["cmaes"])
    assert off.stop_reason == "max_iter" and off.settings["min_step"] == 0.0
    with pytest.raises(ValueError, match="min_step"):
        optimize(bowl, LO, HI, method="cmaes", min_step=-1.0)
    with pytest.raises(TypeError, match="min_step"):
        optimize(bowl, LO, HI, method="pso", min_step=1e-3)


def test_warm_up_imports_the_cmaes_library_in_the_background_and_nothing_for_pso():
    # a fresh interpreter: this one has imported cma already
    code = (
        "import sys\n"
        "from uw_sil.fit.optimize import warm_up\n"
        "assert warm_up('pso') is None and 'cma' not in sys.modules\n"
        "t = warm_up('pso', 'cmaes')\n"
        "t.join(60)\n"
        "assert t.daemon and not t.is_alive() and 'cma' in sys.modules\n"
        "try:\n"
        "    warm_up('nelder-mead')\n"
        "except ValueError as e:\n"
        "    assert 'nelder-mead' in str(e) and 'pso, cmaes' in str(e)\n"
        "else:\n"
        "    raise AssertionError('no error')\n"
        "print('ok')\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr[-2000:]
