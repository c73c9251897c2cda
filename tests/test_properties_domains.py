"""Property tests (hypothesis) for the functions tests/test_properties.py does not reach: the
helpers (``needs_reintegration``, ``whitened_residual``, ``compose``,
``discrete_process_noise``), ``allan.fit_noise``, ``montecarlo.chi2_interval`` and
``monte_carlo``'s parameters, ``calibration_problem`` and ``calibrate``'s parameters, the
``so3`` kernels on Python lists, and the command's numeric options.

The contract is the same as there: a value outside the documented domain raises
``ValueError`` whose message names the argument (or the flag); a valid one returns values
that agree with an independent numpy / scipy computation. Examples are few and
derandomised, and the valid calls reuse a handful of shapes (compile cost).
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import fast_settings as shared_settings
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

import jaximu
from jaximu import ImuBias, ImuNoise, NavState, allan, cli, montecarlo, simulate, so3
from jaximu import calibration as cal


def fast_settings(n):
    return shared_settings(n, HealthCheck.function_scoped_fixture)


BAD_REALS = (np.nan, np.inf, -np.inf, -1.0, 0.0)


def raises_naming(pattern, fn, *args, **kwargs):
    with pytest.raises(ValueError) as err:
        fn(*args, **kwargs)
    assert re.search(pattern, str(err.value)), str(err.value)


# --------------------------------------------------------------------------- helpers

GYRO = np.random.default_rng(0).normal(0, 0.3, (2, 4, 3))
ACCEL = np.r_[0, 0, 9.81] + np.random.default_rng(1).normal(0, 0.5, (2, 4, 3))
PIMS = {
    noisy: jaximu.preintegrate(GYRO, ACCEL, 0.01, noise=ImuNoise.euroc() if noisy else None)
    for noisy in (False, True)
}


def one(pim, i):
    return jax.tree_util.tree_map(lambda x: x[i], pim)


@fast_settings(25)
@given(st.data())
def test_needs_reintegration_domain_and_values(data):
    pim = PIMS[True]
    rng = np.random.default_rng(data.draw(st.integers(0, 2**31), label="seed"))
    b_g, b_a = rng.normal(0, 0.02, (2, 3)), rng.normal(0, 0.1, (2, 3))
    thr = [0.01, 0.10]
    fault = data.draw(
        st.sampled_from((None, None, "b_g", "b_a", "gyro_threshold", "accel_threshold")),
        label="fault",
    )
    if fault in ("b_g", "b_a"):
        (b_g if fault == "b_g" else b_a)[
            data.draw(st.integers(0, 1)), data.draw(st.integers(0, 2))
        ] = data.draw(st.sampled_from((np.nan, np.inf)))
        raises_naming(
            rf"bias\.{fault} contains non-finite",
            jaximu.needs_reintegration,
            pim,
            ImuBias(b_g, b_a),
        )
        return
    if fault:
        thr[0 if fault == "gyro_threshold" else 1] = data.draw(
            st.sampled_from((np.nan, np.inf, -0.1))
        )
        raises_naming(
            rf"{fault} must be non-negative and finite",
            jaximu.needs_reintegration,
            pim,
            ImuBias(b_g, b_a),
            *thr,
        )
        return
    got = np.asarray(jaximu.needs_reintegration(pim, ImuBias(b_g, b_a), *thr))
    want = (np.linalg.norm(b_g - np.asarray(pim.bias_hat.b_g), axis=-1) > thr[0]) | (
        np.linalg.norm(b_a - np.asarray(pim.bias_hat.b_a), axis=-1) > thr[1]
    )
    np.testing.assert_array_equal(got, want)


@fast_settings(10)
@given(st.data())
def test_whitened_residual_needs_noise_and_matches_numpy(data):
    noisy = data.draw(st.booleans(), label="noise")
    i = data.draw(st.integers(0, 1), label="window")
    pim = one(PIMS[noisy], i)
    rng = np.random.default_rng(i)
    s_i = NavState.identity((), jnp.float64)
    s_j = NavState(
        jnp.asarray(so3.exp(rng.normal(0, 0.1, 3))),
        *(jnp.asarray(rng.normal(0, 0.1, 3)) for _ in range(4)),
    )
    if not noisy:
        raises_naming(r"pim\.cov15 is singular.*noise=", jaximu.whitened_residual, s_i, s_j, pim)
        return
    r = np.asarray(jaximu.residual(s_i, s_j, pim))
    L = np.linalg.cholesky(np.asarray(pim.cov15))
    np.testing.assert_allclose(
        np.asarray(jaximu.whitened_residual(s_i, s_j, pim)),
        np.linalg.solve(L, r),
        rtol=1e-8,
        atol=1e-8,
    )


@fast_settings(12)
@given(st.data())
def test_compose_batches(data):
    shapes = ((), (2,), (1,))
    a = data.draw(st.sampled_from(shapes), label="ab batch")
    b = data.draw(st.sampled_from(shapes + ((3,),)), label="bc batch")

    def pim_of(shape):
        p = PIMS[True]
        if shape == ():
            return one(p, 0)
        if shape == (1,):
            return jax.tree_util.tree_map(lambda x: x[:1], p)
        if shape == (3,):
            return jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:1]]), p)
        return p

    try:
        want = np.broadcast_shapes(a, b)
    except ValueError:
        raises_naming(
            r"pim_ab and pim_bc have batch shapes .* which do not broadcast",
            jaximu.compose,
            pim_of(a),
            pim_of(b),
        )
        return
    out = jaximu.compose(pim_of(a), pim_of(b))
    assert out.delta_q.shape == want + (4,)
    np.testing.assert_allclose(np.asarray(out.delta_t), 0.08)


@fast_settings(20)
@given(st.data())
def test_discrete_process_noise_dt_domain(data):
    G = np.zeros((15, 12))
    G[np.arange(12) + 3, np.arange(12)] = 1.0
    n = ImuNoise.euroc()
    form = data.draw(st.sampled_from(("scalar", "array")), label="form")
    bad = data.draw(st.sampled_from((None, None) + BAD_REALS), label="bad")
    dt = 0.01 if form == "scalar" else np.full(2, 0.01)
    if bad is not None:
        if form == "scalar":
            dt = bad
        else:
            dt[data.draw(st.integers(0, 1), label="index")] = bad
        raises_naming(r"dt must be positive and finite", jaximu.discrete_process_noise, G, n, dt)
        return
    Q = np.asarray(jaximu.discrete_process_noise(G, n, dt))
    var = (
        np.repeat(
            [
                n.gyroscope_noise_density**2,
                n.accelerometer_noise_density**2,
                n.gyroscope_random_walk**2,
                n.accelerometer_random_walk**2,
            ],
            3,
        )
        / 0.01
    )
    np.testing.assert_allclose(
        np.diagonal(Q, axis1=-2, axis2=-1)[..., 3:],
        np.broadcast_to(var, Q.shape[:-2] + (12,)),
        rtol=1e-10,
    )


@fast_settings(25)
@given(st.data())
def test_fit_noise_domain_and_recovery(data):
    taus = np.logspace(-2, 2, 12)
    white, walk = data.draw(
        st.sampled_from(((1e-3, 0.0), (1e-4, 1e-5), (0.0, 1e-4))), label="densities"
    )
    adev = np.sqrt(white**2 / taus + walk**2 * taus / 3)
    cols = data.draw(st.booleans(), label="columns")
    if cols:
        adev = np.stack([adev] * 3, axis=1)
    fault = data.draw(st.sampled_from((None, None, "adev", "taus", "length")), label="fault")
    if fault == "adev":
        adev.flat[data.draw(st.integers(0, adev.size - 1))] = data.draw(
            st.sampled_from((np.nan, np.inf, 0.0, -1.0))
        )
        raises_naming(r"adev (contains non-finite|must be positive)", allan.fit_noise, taus, adev)
        return
    if fault == "taus":
        taus = taus.copy()
        taus[data.draw(st.integers(0, 11))] = data.draw(st.sampled_from(BAD_REALS))
        raises_naming(r"taus must be positive and finite", allan.fit_noise, taus, adev)
        return
    if fault == "length":
        raises_naming(r"taus and adev have different lengths", allan.fit_noise, taus[:-1], adev)
        return
    fit = allan.fit_noise(taus, adev)
    np.testing.assert_allclose(fit.white, white, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(fit.random_walk, walk, rtol=1e-6, atol=1e-12)


@fast_settings(25)
@given(confidence=st.floats(-1.0, 200.0), dof=st.sampled_from((150, 1500, 0, -3)))
def test_chi2_interval_matches_scipy_inside_its_domain(confidence, dof):
    from scipy.stats import chi2

    if dof <= 0:
        raises_naming(r"dof must be positive", montecarlo.chi2_interval, dof, 0.95)
    elif not 0 < confidence < 1:
        raises_naming(r"confidence must be in \(0, 1\)", montecarlo.chi2_interval, dof, confidence)
    elif 1e-6 < confidence < 1 - 1e-6:
        np.testing.assert_allclose(
            montecarlo.chi2_interval(dof, confidence), chi2.interval(confidence, dof), rtol=2e-3
        )


MC_BAD = {
    "n_runs": (1, 0, -5, 2.5, "ten"),
    "record_every": (0, -1, 1.5, np.nan),
    "chunk_size": (0, -4, 0.5),
    "n_keep": (-1, 0.5),
    "confidence": (0.0, 1.0, 95, -0.1),
    "gravity": (-9.81, np.nan),
    "scheme": ("heun", "RK4"),
    "b_g0": (np.zeros(2), np.full(3, np.nan)),
    "times": (np.array([0.0, 0.01, 0.01]),),
}


@fast_settings(30)
@given(st.data())
def test_monte_carlo_parameters_outside_their_domain_are_named(data):
    name = data.draw(st.sampled_from(sorted(MC_BAD)), label="parameter")
    value = data.draw(st.sampled_from(MC_BAD[name]), label="value")
    kw = dict(
        trajectory=simulate.circle(),
        times=np.arange(5) * 0.01,
        P0=np.eye(15) * 1e-6,
        noise=ImuNoise.euroc(),
        n_runs=4,
        key=jax.random.PRNGKey(0),
    )
    kw[name] = value
    pattern = {"scheme": "unknown scheme", "times": "times must increase strictly"}.get(
        name, re.escape(name)
    )
    raises_naming(pattern, montecarlo.monte_carlo, **kw)


# --------------------------------------------------------------------------- calibration


@pytest.fixture(scope="module")
def still():
    t = np.arange(301) / 100.0
    ref = cal.Reference(
        t, np.tile([1.0, 0, 0, 0], (301, 1)), np.zeros((301, 3)), np.zeros((301, 3))
    )
    return t, np.zeros((301, 3)), np.tile([0.0, 0, 9.81], (301, 1)), ref


CP_BAD = {
    "keyframe_interval": (0.0, -0.5, np.nan, np.inf, 0.001),
    "windows_per_group": (0, -1, 2.5),
    "reference_sigma": ((1.0, 2.0), (-1.0, 0, 0), (np.nan, 0, 0), 0.1),
}
CAL_BAD = {
    "steps": (0, -3, 1.5),
    "learning_rate": (0.0, -1.0, np.nan),
    "tol": (-1.0, np.nan),
    "max_reduced_chi2": (0.0, -5.0, np.inf),
}


@fast_settings(25)
@given(data=st.data())
def test_calibration_parameters_outside_their_domain_are_named(data, still):
    t, g, a, ref = still
    which = data.draw(st.sampled_from(("problem", "calibrate")), label="function")
    table = CP_BAD if which == "problem" else CAL_BAD
    name = data.draw(st.sampled_from(sorted(table)), label="parameter")
    value = data.draw(st.sampled_from(table[name]), label="value")
    if which == "problem":
        raises_naming(
            re.escape(name),
            cal.calibration_problem,
            t,
            g,
            a,
            ref,
            ImuNoise.euroc(),
            **{name: value},
        )
    else:
        problem = _still_problem(still)
        raises_naming(re.escape(name), cal.calibrate, problem, **{name: value})


_PROBLEM = {}


def _still_problem(still):
    if "p" not in _PROBLEM:
        t, g, a, ref = still
        _PROBLEM["p"] = cal.calibration_problem(t, g, a, ref, ImuNoise.euroc())
    return _PROBLEM["p"]


# --------------------------------------------------------------------------- so3 on lists


@fast_settings(20)
@given(
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
)
def test_so3_lists_equal_arrays(phi, q):
    q = list(np.asarray(q) / np.linalg.norm(q))
    for f, args in (
        (so3.exp, (phi,)),
        (so3.quat_to_matrix, (q,)),
        (so3.log, (q,)),
        (so3.quat_rotate, (q, phi)),
        (so3.skew, (phi,)),
        (so3.xyzw_to_wxyz, (q,)),
        (so3.quat_mul, (q, q)),
    ):
        np.testing.assert_allclose(
            np.asarray(f(*args)), np.asarray(f(*(jnp.asarray(x) for x in args))), atol=1e-12
        )


# --------------------------------------------------------------------------- command options

DATA = "tests/data/tumvi_room4"
CLI_BAD = [
    (["demo"], "--seconds", ("0", "-1", "nan", "21", "inf")),
    (["montecarlo", "--runs", "4"], "--seconds", ("0", "-2", "nan", "inf", "0.001")),
    (["montecarlo", "--runs", "4"], "--rate", ("0", "-200", "nan")),
    (["montecarlo"], "--runs", ("1", "0", "-3")),
    (["propagate", DATA], "--gravity", ("nan", "-9.81", "inf")),
    (["propagate", DATA], "--still", ("0", "-1", "nan")),
    (["propagate", DATA], "--start", ("-1", "nan")),
    (["propagate", DATA], "--duration", ("0", "-1", "nan")),
    (["propagate", DATA], "--max-gap", ("0", "-0.1", "nan")),
    (["preintegrate", DATA], "--window", ("0", "-0.5", "nan")),
    (["calibrate", DATA], "--keyframe-interval", ("0", "-0.5", "nan")),
    (["calibrate", DATA], "--steps", ("0", "-1")),
]


@fast_settings(40)
@given(data=st.data())
def test_command_options_outside_their_domain_name_the_flag(data, capsys):
    base, flag, values = data.draw(st.sampled_from(CLI_BAD), label="option")
    value = data.draw(st.sampled_from(values), label="value")
    code = cli.main(
        base + [f"{flag}={value}", "--no-progress"]
        if base[0] != "preintegrate" and base[0] != "calibrate"
        else base + [f"{flag}={value}"]
    )
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1 and flag in lines[0], err
    assert "read " not in out  # refused before reading the recording
