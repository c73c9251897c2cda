"""Property-based tests (hypothesis): random, extreme and empty inputs at the public API.

Two contracts, by kind of function:

1. **Validated entry points** - ``propagate``, ``propagate_final``, ``propagate_covariance``,
   ``propagate_covariance_final``, ``preintegrate``, ``correct``, ``predict``, ``residual``
   and ``allan.allan_deviation``. For any input (shapes from small fixed sets, float32 /
   float64 / int arrays, NaN, ±inf, zero / negative / huge / tiny ``dt``, huge samples,
   ``T = 0``, zero-size batches, wrong shapes) an eager call either returns outputs that are
   all finite, or raises ``ValueError`` whose message names the problem (the input, or "too
   large" for an overflow of the computation dtype). Never another exception type, a warning
   (``filterwarnings = error``), or a silent NaN/inf result. Inputs that are valid and of
   moderate size must succeed. Each example records what it broke: an invalid input *must*
   raise and the message must name one of the problems injected; a huge but finite value
   *may* raise (the result would overflow) with "too large".

2. **Pure array kernels** - ``jaximu.so3.*`` and ``boxplus`` / ``boxminus``: no value
   validation by design (they run inside ``jit``/``grad`` loops). Finite input of moderate
   magnitude (angles up to ~100 rad) gives finite output, quaternions out are unit, on
   every batch shape (including zero-size) and for float32, float64 and integer input.
   ``boxplus``/``boxminus`` also check shapes and types (``ValueError``).

The library defects these properties found (overflow returned as NaN/inf, values that do
not fit the computation dtype, unclear batch and type errors, ``allan_deviation`` warnings)
are also pinned by plain regression tests below the properties.

Compile cost: the suite is bound by XLA compilation, and every new (shape, dtype, static
argument) compiles, so shapes come from small fixed sets (``T`` in {0, 1, 2, 3}, batch in
{(), (2,), (0,)}), examples are few and the runs are derandomised (reproducible).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import fast_settings
from hypothesis import given
from hypothesis import strategies as st

import jaximu
from jaximu import ImuBias, ImuNoise, NavState, allan, so3

TOO_LARGE = r"too large|out of its range"
DT_BAD = r"dt must be positive and finite"
F32_MAX = float(np.finfo(np.float32).max)


class Expect:
    """What a call may do. ``bad``: an invalid input, so it must raise ``ValueError``;
    ``may``: a huge finite value, so it may raise. Either way the message must match one of
    the recorded patterns."""

    def __init__(self):
        self.allowed: list[str] = []
        self.must = False

    def bad(self, pattern):
        self.allowed.append(pattern)
        self.must = True

    def may(self, pattern=TOO_LARGE):
        self.allowed.append(pattern)


def assert_finite(out):
    for path, leaf in jax.tree_util.tree_leaves_with_path(out):
        arr = np.asarray(leaf)
        if np.issubdtype(arr.dtype, np.inexact):
            assert np.isfinite(arr).all(), f"non-finite output{jax.tree_util.keystr(path)}"


def check_call(expect: Expect, fn, *args, **kwargs):
    """The property: all-finite outputs, or a ``ValueError`` that names a problem injected."""
    try:
        out = fn(*args, **kwargs)
    except ValueError as e:
        msg = str(e)
        assert expect.allowed, f"valid input of moderate size raised: {msg}"
        assert any(re.search(p, msg) for p in expect.allowed), (
            f"message {msg!r} names none of the problems {expect.allowed}"
        )
        return None
    assert not expect.must, f"invalid input {expect.allowed} returned instead of raising"
    assert_finite(out)
    return out


# --------------------------------------------------------------------------- input strategies
#
# Each test runs once with valid inputs only (``target=None``: random, integer or zero
# samples, scalar / per-sample / per-interval / batched ``dt``, shared or batched state,
# shapes from the small sets) and once per ``target`` (pytest parameter, so every kind of
# fault is covered whatever hypothesis draws): only that input is drawn from its invalid or
# extreme kinds. Errors are raised before any compilation and stay cheap.

BENIGN = ("normal", "normal", "int", "zero")
HOT = ("nan", "inf", "huge", "huge")


def rng_of(data):
    return np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))


def inject(data, x, value):
    """Set one random element of ``x`` (a numpy array) to ``value``; False if ``x`` is empty."""
    if x.size == 0:
        return False
    x.flat[data.draw(st.integers(0, x.size - 1), label="index")] = value
    return True


def huge_value(data, dtype):
    v = data.draw(st.sampled_from((1e20, 1e30, 3e38, 1e300)), label="huge")
    return min(v, 0.9 * F32_MAX) if dtype == np.float32 else v


def draw_array(data, name, shape, dtype, expect, hot, center=0.0, scale=2.0):
    """``shape`` array of ``dtype`` (or int64); ``hot``: with one NaN, -inf or huge entry."""
    kind = data.draw(st.sampled_from(HOT if hot else BENIGN), label=f"{name} kind")
    x = center + rng_of(data).uniform(-scale, scale, shape)
    if kind == "int":
        return np.round(x).astype(np.int64)
    x = np.zeros(shape, dtype) if kind == "zero" else x.astype(dtype)
    if kind in ("nan", "inf") and inject(data, x, np.nan if kind == "nan" else -np.inf):
        expect.bad(rf"{re.escape(name)} contains non-finite")
    if kind == "huge" and inject(data, x, huge_value(data, dtype)):
        expect.may()
    return x


def draw_dt(data, T, batch, expect, hot):
    """``dt`` as a Python float or a float32/float64/int array; scalar, per sample, per interval
    or batched. ``hot``: a zero / negative / NaN / inf / huge / tiny entry, or a wrong length."""
    forms = ("scalar", "samples", "batched") + (("intervals",) if T > 1 else ())
    form = data.draw(st.sampled_from(forms), label="dt form")
    dtype = data.draw(st.sampled_from((np.float64, np.float32)), label="dt dtype")
    kinds = (
        ("zero", "negative", "nan", "inf", "huge", "tiny", "length")
        if hot
        else ("normal", "normal", "int")
    )
    kind = data.draw(st.sampled_from(kinds), label="dt kind")
    shape = {"scalar": (), "samples": (T,), "intervals": (T - 1,), "batched": tuple(batch) + (T,)}[
        form
    ]
    if kind == "length":
        shape = shape[:-1] + (T + 1,) if shape else (T + 1,)
        expect.bad(r"dt must be a scalar or have shape")
    dt = rng_of(data).uniform(1e-3, 0.05, shape).astype(dtype)
    if kind == "int":
        dt = np.ones(shape, np.int64)
    bad = {"zero": 0.0, "negative": -0.01, "nan": np.nan, "inf": np.inf}
    if kind in bad and inject(data, dt, bad[kind]):
        expect.bad(DT_BAD)
    if kind == "huge":
        v = data.draw(st.sampled_from((1e30, 1e300)), label="huge dt")
        if inject(data, dt, min(v, 0.9 * F32_MAX) if dtype == np.float32 else v):
            expect.may(rf"{DT_BAD}|{TOO_LARGE}")
    if kind == "tiny":  # 1e-300 is 0 in a float32 array, and 0 in a float32 computation
        v = data.draw(st.sampled_from((1e-45, 1e-300)), label="tiny dt")
        if inject(data, dt, v):
            expect.may(rf"{DT_BAD}|{TOO_LARGE}")
    if not shape and data.draw(st.booleans(), label="python float dt"):
        dt = dt.item()
    return dt


def draw_imu(data, expect, dtype, target):
    """``(gyro, accel, dt, batch)``: ``T`` in {1, 2, 3} and batch in {(), (2,), (0,)}; with
    ``target == "shape"`` one shape fault (``T = 0``, mismatched ``T``, last axis, batch)."""
    fault = (
        data.draw(st.sampled_from(("T=0", "samples", "axis", "batch")), label="fault")
        if target == "shape"
        else None
    )
    T = 0 if fault == "T=0" else data.draw(st.sampled_from((1, 3, 2)), label="T")
    batch = data.draw(st.sampled_from(((), (2,), (0,))), label="batch")
    gyro = draw_array(data, "gyro", batch + (T, 3), dtype, expect, target == "gyro")
    accel = draw_array(
        data, "accel", batch + (T, 3), dtype, expect, target == "accel", center=np.r_[0, 0, 9.81]
    )
    dt = draw_dt(data, max(T, 1), batch, expect, target == "dt")
    if fault == "T=0":
        expect.bad("no samples")
    elif fault == "samples":
        accel = np.concatenate([accel, accel[..., :1, :]], axis=-2)
        expect.bad("different numbers of samples")
    elif fault == "axis":
        gyro = np.concatenate([gyro, gyro[..., :1]], axis=-1)
        expect.bad(r"gyro must have shape \(\.\.\., T, 3\)")
    elif fault == "batch":
        accel = np.concatenate([accel[None]] * 3, axis=0)
        gyro = np.concatenate([gyro[None]] * 2, axis=0)
        expect.bad("do not broadcast")
    return gyro, accel, dt, batch


def draw_state(data, expect, dtype, batch, hot, name="state"):
    """A :class:`NavState` with a unit ``q`` (float or integer), shared or batched; ``hot``: a
    non-unit ``q``, a NaN, a huge value or a wrongly shaped field."""
    sbatch = data.draw(st.sampled_from(((), batch)), label=f"{name} batch")
    rng = rng_of(data)
    q = rng.normal(size=sbatch + (4,))
    q = (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(dtype)
    f = {
        "q": q,
        **{k: rng.normal(size=sbatch + (3,)).astype(dtype) for k in ("p", "v", "b_g", "b_a")},
    }
    kinds = ("nonunit", "nan", "huge", "huge", "shape") if hot else ("ok", "ok", "int_q")
    kind = data.draw(st.sampled_from(kinds), label=f"{name} kind")
    field = data.draw(st.sampled_from(("p", "v", "b_g", "b_a")), label=f"{name} field")
    if kind == "nonunit" and q.size:
        f["q"] = q * np.asarray(1.01, dtype)
        expect.bad(rf"{name}\.q is not a unit quaternion")
    elif kind == "nan" and inject(data, f[field], np.nan):
        expect.bad(rf"{name}\.{field} contains non-finite")
    elif kind == "huge":
        # a float64 field next to a float32 q: the computation dtype may still be float32
        f[field] = f[field].astype(
            data.draw(st.sampled_from((np.float64, dtype)), label="field dtype")
        )
        if inject(data, f[field], huge_value(data, f[field].dtype.type)):
            expect.may()
    elif kind == "int_q":
        f["q"] = np.broadcast_to(np.array([1, 0, 0, 0]), sbatch + (4,))
    elif kind == "shape":
        f[field] = f[field][..., :2]
        expect.bad(rf"{name}\.{field} must have shape")
    return NavState(**f)


def draw_gravity(data, expect, hot):
    kinds = ("nan", "huge", "shape") if hot else ("default", "magnitude", "vector")
    kind = data.draw(st.sampled_from(kinds), label="gravity kind")
    if kind == "default":
        return {}
    g = {
        "magnitude": 9.81,
        "vector": np.array([0.1, 0.0, -9.8]),
        "nan": np.nan,
        "huge": 1e300,
        "shape": np.zeros(2),
    }[kind]
    if kind == "nan":
        expect.bad("gravity contains non-finite")
    elif kind == "huge":
        expect.may()
    elif kind == "shape":
        expect.bad("gravity must be a magnitude")
    return {"gravity": g}


def draw_noise(data, expect, hot):
    kinds = ("nan", "negative", "huge", "type") if hot else ("euroc", "zero", "axes")
    kind = data.draw(st.sampled_from(kinds), label="noise kind")
    if kind == "type":
        expect.bad("noise must be a jaximu.ImuNoise")
        return (1e-3, 1e-2, 0.0, 0.0)
    vals = {
        "euroc": (1.7e-4, 2e-3, 1.9e-5, 3e-3),
        "zero": (0.0, 0.0, 0.0, 0.0),
        "nan": (np.nan, 2e-3, 0.0, 0.0),
        "negative": (1.7e-4, -2e-3, 0.0, 0.0),
        "huge": (1.7e-4, 2e-3, 1e300, 0.0),
        "axes": (np.full(3, 1.7e-4), np.full(3, 2e-3), 1.9e-5, 3e-3),
    }[kind]
    if kind == "nan":
        expect.bad("noise.gyroscope_noise_density contains non-finite")
    elif kind == "negative":
        expect.bad("noise.accelerometer_noise_density must be non-negative")
    elif kind == "huge":
        expect.may()
    return ImuNoise(*vals)


def draw_dtype(data):
    return data.draw(st.sampled_from((np.float64, np.float32)), label="dtype")


# --------------------------------------------------------------------------- contract 1


def run_propagate(data, target):
    expect = Expect()
    dtype = draw_dtype(data)
    gyro, accel, dt, batch = draw_imu(data, expect, dtype, target)
    state = draw_state(data, expect, dtype, batch, target == "state")
    kw = draw_gravity(data, expect, target == "gravity")
    scheme = data.draw(st.sampled_from(("euler", "midpoint", "rk4")), label="scheme")
    attitude = data.draw(
        st.sampled_from(("quaternion",) * 4 + ("matrix", "euler_angles")), label="attitude"
    )
    if target == "option":
        scheme, attitude = data.draw(
            st.sampled_from(((scheme, "rodrigues"), ("heun", attitude))), label="option"
        )
        expect.bad("unknown scheme 'heun'|unknown attitude form 'rodrigues'")
    if attitude == "euler_angles":
        expect.may("singularity")  # huge rates can reach pitch ±90°
    fn = data.draw(st.sampled_from((jaximu.propagate, jaximu.propagate_final)), label="fn")
    check_call(expect, fn, state, gyro, accel, dt, scheme, attitude=attitude, **kw)


def draw_p0(data, expect, batch, hot):
    kinds = (
        ("nan", "asym", "indefinite", "huge", "shape", "batch")
        if hot
        else ("ok", "batched") + (("empty",) if batch in ((), (0,)) else ())
    )
    kind = data.draw(st.sampled_from(kinds), label="P0 kind")
    P0 = np.eye(15) * 1e-4
    if kind == "batched":
        P0 = np.broadcast_to(P0, batch + (15, 15))
    elif kind == "empty":  # a zero-size batch of covariances
        P0 = np.zeros((0, 15, 15))
    elif kind == "batch":
        P0 = np.broadcast_to(P0, (5, 15, 15))
        if batch:
            expect.bad("do not broadcast")
    elif kind == "nan":
        P0 = np.full((15, 15), np.nan)
        expect.bad("P0 contains non-finite")
    elif kind == "asym":
        P0 = P0 + np.triu(np.ones((15, 15)), 1)
        expect.bad("P0 is not symmetric")
    elif kind == "indefinite":
        P0 = -P0
        expect.bad("P0 is not positive semi-definite")
    elif kind == "huge":  # 1e300 does not fit a float32 computation
        P0 = np.eye(15) * data.draw(st.sampled_from((1e30, 1e300)), label="huge P0")
        expect.may()
    elif kind == "shape":
        P0 = np.eye(14)
        expect.bad(r"P0 must have shape \(\.\.\., 15, 15\)")
    if np.abs(P0).max(initial=0.0) < F32_MAX:
        P0 = P0.astype(data.draw(st.sampled_from((np.float64, np.float32)), label="P0 dtype"))
    return P0


def run_propagate_covariance(data, target):
    expect = Expect()
    dtype = draw_dtype(data)
    gyro, accel, dt, batch = draw_imu(data, expect, dtype, target)
    state = draw_state(data, expect, dtype, batch, target == "state")
    kw = draw_gravity(data, expect, target == "gravity")
    noise = draw_noise(data, expect, target == "noise")
    P0 = draw_p0(data, expect, batch, target == "P0")
    scheme = data.draw(st.sampled_from(("euler", "midpoint", "rk4")), label="scheme")
    fn = data.draw(
        st.sampled_from((jaximu.propagate_covariance_final, jaximu.propagate_covariance)),
        label="fn",
    )
    check_call(expect, fn, state, P0, gyro, accel, dt, noise, scheme, **kw)


def draw_bias(data, expect, dtype, batch, hot):
    kinds = ("nan", "huge", "shape", "type") if hot else ("none", "zero", "random", "batched")
    kind = data.draw(st.sampled_from(kinds), label="bias kind")
    if kind == "none":
        return None
    if kind == "type":
        expect.bad("bias must be a jaximu.ImuBias")
        return (0.0, 0.0)
    shape = (batch if kind == "batched" else ()) + (3,)
    rng = rng_of(data)
    b_g, b_a = (rng.normal(0, 0.1, shape).astype(dtype) for _ in range(2))
    if kind == "zero":
        b_g, b_a = np.zeros(3, dtype), np.zeros(3, dtype)
    elif kind == "nan":
        b_a[1] = np.nan
        expect.bad(r"bias\.b_a contains non-finite")
    elif kind == "huge":  # a float64 bias with float32 samples may not fit the dtype
        b_g = b_g.astype(np.float64)
        b_g[0] = 1e300
        expect.may()
    elif kind == "shape":
        b_g = b_g[..., :2]
        expect.bad(r"bias\.b_g must have shape")
    return ImuBias(b_g, b_a)


def run_preintegrate(data, target):
    expect = Expect()
    dtype = draw_dtype(data)
    gyro, accel, dt, batch = draw_imu(data, expect, dtype, target)
    bias = draw_bias(data, expect, dtype, batch, target == "bias")
    noise = (
        draw_noise(data, expect, True)
        if target == "noise"
        else data.draw(st.sampled_from((None, ImuNoise.euroc())), label="noise")
    )
    scheme = data.draw(st.sampled_from(("euler", "midpoint")), label="scheme")
    method = data.draw(st.sampled_from(("sequential", "parallel")), label="method")
    if target == "option":
        scheme = "rk4"
        expect.bad("unknown preintegration scheme 'rk4'")
    prefixes = data.draw(st.sampled_from((False, False, True)), label="prefixes")
    check_call(
        expect, jaximu.preintegrate, gyro, accel, dt, bias, noise, scheme, method, prefixes=prefixes
    )


_PIMS = {}


def a_pim(dtype, batch):
    """A preintegrated measurement of batch () or (2,), built once per dtype (compile cost)."""
    key = np.dtype(dtype).name
    if key not in _PIMS:
        rng = np.random.default_rng(0)
        gyro = rng.normal(0, 0.5, (2, 3, 3)).astype(dtype)
        accel = (np.r_[0, 0, 9.81] + rng.normal(0, 1, (2, 3, 3))).astype(dtype)
        _PIMS[key] = jaximu.preintegrate(
            gyro, accel, np.asarray(0.01, dtype), noise=ImuNoise.euroc()
        )
    return _PIMS[key] if batch else jax.tree_util.tree_map(lambda x: x[0], _PIMS[key])


def run_use(data, fn, target):
    """:func:`jaximu.correct`, :func:`jaximu.predict` or :func:`jaximu.residual`."""
    expect = Expect()
    dtype = draw_dtype(data)
    batch = data.draw(st.sampled_from(((), (2,))), label="pim batch")
    pim = a_pim(dtype, batch)
    if target == "pim":
        if data.draw(st.booleans(), label="pim NaN"):
            delta_v = np.array(pim.delta_v)
            delta_v[..., 1] = np.nan
            pim = jaximu.Preintegrated(
                pim.delta_t,
                pim.delta_q,
                delta_v,
                pim.delta_p,
                pim.transition,
                pim.cov15,
                pim.cov,
                pim.bias_hat,
            )
            expect.bad(r"pim\.delta_v contains non-finite")
        else:
            pim = (pim.delta_q, pim.delta_v)
            expect.bad("pim must be a jaximu.Preintegrated")
    if fn == "correct":
        bias = draw_bias(data, expect, dtype, batch, target == "bias")
        if bias is None:
            bias = ImuBias.zeros((), dtype)
        if target == "bias batch":  # (3,) does not broadcast to the pim's batch () or (2,)
            bias = ImuBias.zeros((3,), dtype)
            expect.bad("does not broadcast|do not broadcast")
        check_call(expect, jaximu.correct, pim, bias)
        return
    state_i = draw_state(data, expect, dtype, batch, target == "state_i", "state_i")
    kw = draw_gravity(data, expect, target == "gravity")
    if fn == "predict":
        check_call(expect, jaximu.predict, state_i, pim, **kw)
    else:
        state_j = draw_state(data, expect, dtype, batch, target == "state_j", "state_j")
        check_call(expect, jaximu.residual, state_i, state_j, pim, **kw)


def run_allan(data, target):
    expect = Expect()
    n, cols = 40, data.draw(st.sampled_from((None, 3, 1, 0)), label="columns")
    if target == "shape":
        n, cols = data.draw(st.sampled_from(((9, None), (0, 3), (40, "3d"))), label="shape")
        expect.bad(r"need at least 10 samples|y must have shape \(N,\) or \(N, d\)")
    shape = (n,) if cols is None else (n, 2, 2) if cols == "3d" else (n, cols)
    y = draw_array(data, "y", shape, draw_dtype(data), expect, target == "y", scale=1.0)
    if target == "y":  # huge samples: their squares overflow float64
        if y.dtype == np.float64 and data.draw(st.booleans(), label="near the float64 maximum"):
            inject(data, y, 1.5e308)
        expect.may(r"overflowed float64")
    dts = (np.nan, np.inf, 0.0, -1.0, 1e300, 1e-320, "array") if target == "dt" else (0.01, 1.0, 1)
    dt = data.draw(st.sampled_from(dts), label="dt")
    if isinstance(dt, str):
        dt = np.array([0.01, 0.02])
        expect.bad("dt must be a scalar")
    elif not (np.isfinite(dt) and dt > 0):
        expect.bad("dt must be positive and finite")
    elif dt in (1e300, 1e-320):
        expect.may(r"overflowed float64")
    taus = data.draw(
        st.sampled_from(
            ([np.nan], [-1.0], [1e300], [np.inf])
            if target == "taus"
            else (None, None, [0.05, 0.1], [])
        ),
        label="taus",
    )
    if target == "taus":
        expect.bad("every τ must be positive and finite|shorter than half the recording")
    elif taus and dt == 1e-320:  # τ = 0.05 s is 5e318 samples
        expect.may("shorter than half the recording")
    ppd = data.draw(st.sampled_from((0, -1) if target == "ppd" else (10, 3)), label="ppd")
    if target == "ppd" and taus is None:
        expect.bad("points_per_decade must be positive")
    check_call(expect, allan.allan_deviation, y, dt, taus, ppd)


# The properties: valid inputs (every shape, dtype and form) return finite outputs; each
# kind of bad or extreme input raises a ValueError naming it, or returns finite outputs.

PROPAGATE_TARGETS = ("gyro", "accel", "dt", "state", "gravity", "shape", "option")
COVARIANCE_TARGETS = ("gyro", "accel", "dt", "state", "gravity", "shape", "noise", "P0")
PREINTEGRATE_TARGETS = ("gyro", "accel", "dt", "bias", "noise", "shape", "option")
USE_TARGETS = (
    [("predict", t) for t in ("pim", "state_i", "gravity")]
    + [("residual", t) for t in ("pim", "state_i", "state_j")]
    + [("correct", t) for t in ("pim", "bias", "bias batch")]
)
ALLAN_TARGETS = ("y", "shape", "dt", "taus", "ppd")


@fast_settings(20)
@given(data=st.data())
def test_propagate_valid_inputs_return_finite(data):
    run_propagate(data, None)


@pytest.mark.parametrize("target", PROPAGATE_TARGETS)
@fast_settings(5)
@given(data=st.data())
def test_propagate_bad_inputs_raise_value_error(data, target):
    run_propagate(data, target)


@fast_settings(8)
@given(data=st.data())
def test_propagate_covariance_valid_inputs_return_finite(data):
    run_propagate_covariance(data, None)


@pytest.mark.parametrize("target", COVARIANCE_TARGETS)
@fast_settings(4)
@given(data=st.data())
def test_propagate_covariance_bad_inputs_raise_value_error(data, target):
    run_propagate_covariance(data, target)


@fast_settings(8)
@given(data=st.data())
def test_preintegrate_valid_inputs_return_finite(data):
    run_preintegrate(data, None)


@pytest.mark.parametrize("target", PREINTEGRATE_TARGETS)
@fast_settings(4)
@given(data=st.data())
def test_preintegrate_bad_inputs_raise_value_error(data, target):
    run_preintegrate(data, target)


@pytest.mark.parametrize("fn", ["predict", "residual", "correct"])
@fast_settings(6)
@given(data=st.data())
def test_correct_predict_residual_valid_inputs_return_finite(data, fn):
    run_use(data, fn, None)


@pytest.mark.parametrize("fn,target", USE_TARGETS)
@fast_settings(5)
@given(data=st.data())
def test_correct_predict_residual_bad_inputs_raise_value_error(data, fn, target):
    run_use(data, fn, target)


@fast_settings(20)
@given(data=st.data())
def test_allan_deviation_valid_inputs_return_finite(data):
    run_allan(data, None)


@pytest.mark.parametrize("target", ALLAN_TARGETS)
@fast_settings(10)
@given(data=st.data())
def test_allan_deviation_bad_inputs_raise_value_error(data, target):
    run_allan(data, target)


# The defects these properties found, pinned as plain regression tests.


def test_overflow_from_finite_inputs_is_a_value_error_not_nan():
    """dt = 1e30 in float32 used to return NaN/inf states, covariances and deltas silently."""
    s32 = NavState.identity((), jnp.float32)
    w, a = np.zeros((3, 3), np.float32), np.tile(np.float32([0, 0, 9.81]), (3, 1))
    with pytest.raises(
        ValueError,
        match=r"propagate produced a non-finite value .* in output\.p "
        r"at index \[0, 0\]: dt or the IMU samples are too large "
        r"for float32",
    ):
        jaximu.propagate(s32, w, a, np.float32(1e30))
    with pytest.raises(ValueError, match=r"preintegrate produced a non-finite value.*float64"):
        jaximu.preintegrate(np.full((3, 3), 1e300), np.zeros((3, 3)), 0.01)
    with pytest.raises(
        ValueError,
        match=r"propagate_covariance_final produced a non-finite value"
        r".*output\[1\].*σ²/dt overflows",
    ):
        jaximu.propagate_covariance_final(
            s32, np.eye(15, dtype=np.float32), w, a, np.float32(1e-45), ImuNoise.euroc()
        )
    # the eager check only: under the caller's jit the numbers come back as they are
    out = jax.jit(jaximu.propagate_final)(s32, w, a, np.float32(1e30))
    assert not np.isfinite(np.asarray(out.p)).all()


def test_values_that_do_not_fit_the_computation_dtype_are_named():
    """dt = 1e300 and 1e-300 are inf and 0 in float32 (they used to pass the dt check and give
    NaN, or a numpy overflow warning). A Python scalar is weak (the samples' float32 stays);
    a float64 array makes the computation float64 (contract/test_input_types.py), so a float64
    value in a float32 computation happens without jax_enable_x64: checked in a child
    process."""
    s32 = NavState.identity((), jnp.float32)
    w = np.zeros((2, 3), np.float32)
    with pytest.raises(
        ValueError,
        match=r"dt must be positive and finite; dt = 1e\+300, "
        r"which is inf in the computation dtype float32",
    ):
        jaximu.propagate(s32, w, w, 1e300)
    with pytest.raises(ValueError, match=r"dt = 1e-300, which is 0.0 in the computation dtype"):
        jaximu.preintegrate(w, w, 1e-300)
    code = """if True:
        import numpy as np, jax.numpy as jnp, jaximu
        s32 = jaximu.NavState.identity((), jnp.float32)
        w = np.zeros((2, 3), np.float32)
        cases = [lambda: jaximu.propagate(s32, w, w, np.array([0.01, 1e300])),
                 lambda: jaximu.propagate(s32.replace(p=np.array([0, 1e300, 0])), w, w, 0.01),
                 lambda: jaximu.propagate_covariance(s32, np.eye(15) * 1e300, w, w, 0.01,
                                                     jaximu.ImuNoise.euroc())]
        for case in cases:
            try:
                case()
            except ValueError as e:
                print(e)
    """
    env = {**os.environ, "JAX_ENABLE_X64": "0"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    ).stdout.splitlines()
    assert len(out) == 3, out
    assert re.search(
        r"dt must be positive and finite; dt\[1\] = 1e\+300, which is inf in the "
        r"computation dtype float32",
        out[0],
    ), out[0]
    assert re.search(
        r"state\.p\[1\] = 1e\+300 is too large for the computation dtype "
        r"float32",
        out[1],
    ), out[1]
    assert re.search(r"P0\[0, 0\] = 1e\+300 is too large", out[2]), out[2]


def test_batch_and_type_errors_name_the_problem():
    s = NavState.identity((), jnp.float64)
    w = np.zeros((2, 3))
    with pytest.raises(ValueError, match="batch shapes of the inputs do not broadcast"):
        jaximu.propagate_covariance(
            s,
            np.zeros((3, 15, 15)),
            np.zeros((2, 2, 3)),
            np.zeros((2, 2, 3)),
            0.01,
            ImuNoise.euroc(),
        )
    with pytest.raises(ValueError, match=r"delta must have shape \(\.\.\., 15\)"):
        jaximu.boxplus(s, np.zeros(14))
    pim = jaximu.preintegrate(w, w, 0.01)
    with pytest.raises(ValueError, match="state_i.q is not a unit quaternion"):
        jaximu.predict(s.replace(q=np.array([1.0, 0.1, 0, 0])), pim)
    with pytest.raises(ValueError, match=r"state_j\.v contains non-finite"):
        jaximu.residual(s, s.replace(v=np.array([0, np.nan, 0])), pim)
    # a batch of states against one shared measurement broadcasts (it used to fail)
    assert jaximu.predict(NavState.identity((4,), jnp.float64), pim).p.shape == (4, 3)
    assert jaximu.residual(NavState.identity((4,), jnp.float64), s, pim).shape == (4, 15)


def test_allan_deviation_rejects_what_it_cannot_compute():
    y = np.random.default_rng(0).normal(size=(100, 3))
    for kwargs, message in [
        ({"y": y[:, 0, None, None]}, r"y must have shape \(N,\) or \(N, d\)"),
        ({"y": np.r_[y[:50], [[0, np.nan, 0]], y[51:]]}, "non-finite.*sample 50, column 1"),
        ({"dt": np.inf}, "dt must be positive and finite, got inf"),
        ({"dt": np.array([0.1, 0.1])}, "dt must be a scalar"),
        ({"taus": [np.nan]}, "every τ must be positive and finite"),
        ({"taus": [-1.0]}, "every τ must be positive and finite"),
        ({"y": y * 1e300}, "overflowed float64 .* y or dt is too large"),
    ]:
        with pytest.raises(ValueError, match=message):
            allan.allan_deviation(**{"y": y, "dt": 0.01, **kwargs})


# --------------------------------------------------------------------------- contract 2


KERNEL_BATCHES = ((), (0,), (2, 3))


def unit_tol(dtype):
    return 1e-5 if dtype == np.float32 else 1e-12


def assert_unit(q, dtype):
    q = np.asarray(q, np.float64)
    assert np.isfinite(q).all()
    assert np.all(np.abs(np.linalg.norm(q, axis=-1) - 1) < unit_tol(dtype))


def random_unit_quat(rng, shape, dtype):
    q = rng.normal(size=shape + (4,))
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(dtype)


@jax.jit
def so3_outputs(phi, v, p, q):
    """Every :mod:`jaximu.so3` kernel on one input set (one compilation per shape and dtype):
    ``(unit quaternions, other outputs)``."""
    R = so3.exp_matrix(phi)
    log_q = so3.log(q)
    unit = {
        "exp": so3.exp(phi),
        "quat_mul": so3.quat_mul(p, q),
        "quat_conj": so3.quat_conj(q),
        "quat_normalize": so3.quat_normalize(2 * q),
        "quat_first_order_update": so3.quat_first_order_update(q, phi),
        "matrix_to_quat": so3.matrix_to_quat(so3.quat_to_matrix(q)),
        "matrix_to_quat(exp_matrix)": so3.matrix_to_quat(R),
        "euler_zyx_to_quat": so3.euler_zyx_to_quat(phi),
        "xyzw_to_wxyz": so3.xyzw_to_wxyz(q),
        "wxyz_to_xyzw": so3.wxyz_to_xyzw(q),
        "jpl_to_hamilton": so3.jpl_to_hamilton(q),
        "hamilton_to_jpl": so3.hamilton_to_jpl(q),
        "quat_identity": so3.quat_identity(phi.shape[:-1], phi.dtype),
    }
    chi = phi.at[..., 1].set(jnp.clip(phi[..., 1], -1.4, 1.4))  # E(χ) is singular at ±π/2
    other = {
        "quat_rotate": so3.quat_rotate(q, v),
        "log": log_q,
        "exp_matrix": R,
        "R Rᵀ": R @ jnp.swapaxes(R, -1, -2),
        "log_matrix": so3.log_matrix(R),
        "skew": so3.skew(v),
        "right_jacobian": so3.right_jacobian(phi),
        "left_jacobian": so3.left_jacobian(phi),
        "right_jacobian_inv": so3.right_jacobian_inv(log_q),  # θ ≤ π < 2π
        "euler_zyx_to_matrix": so3.euler_zyx_to_matrix(phi),
        "quat_to_euler_zyx": so3.quat_to_euler_zyx(q),
        "euler_rate_matrix": so3.euler_rate_matrix(chi),
    }
    return unit, other


@jax.jit
def so3_int_outputs(phi, v):
    """The kernels that accept integer vectors (angles, body vectors)."""
    q = so3.exp(phi)
    return (q, so3.quat_first_order_update(q, phi)), (
        so3.skew(v),
        so3.exp_matrix(phi),
        so3.right_jacobian(phi),
        so3.quat_rotate(q, v),
    )


@fast_settings(25)
@given(st.data())
def test_so3_kernels_finite_and_unit_on_moderate_input(data):
    """Finite input of moderate magnitude (angles 0 to 100 rad, zero-size batches, float32,
    float64, integers): finite output, unit quaternions, angles in [0, π], orthonormal R."""
    dtype = data.draw(st.sampled_from((np.float64, np.float32, np.int64)), label="dtype")
    batch = data.draw(st.sampled_from(KERNEL_BATCHES), label="batch")
    scale = data.draw(st.sampled_from((1.0, 1e-4, 0.0, 100.0, 3.1)), label="angle scale")
    rng = rng_of(data)
    phi = rng.uniform(-scale, scale, batch + (3,))
    v = rng.normal(0, 10, batch + (3,))
    if dtype == np.int64:  # integer input: the kernels promote it to a float
        phi, v = np.round(phi).astype(np.int64), np.round(v).astype(np.int64)
        unit, other = so3_int_outputs(jnp.asarray(phi), jnp.asarray(v))
        for x in unit:
            assert_unit(x, np.float32)
        assert_finite(other)
        return
    p, q = (random_unit_quat(rng, batch, dtype) for _ in range(2))
    unit, other = so3_outputs(*(jnp.asarray(x, dtype) for x in (phi, v, p, q)))
    for name, x in unit.items():
        assert x.dtype == dtype, name
        assert_unit(x, dtype)
    assert_finite(other)
    tol = 1e-4 if dtype == np.float32 else 1e-10
    np.testing.assert_allclose(
        np.linalg.norm(np.asarray(other["quat_rotate"], float), axis=-1),
        np.linalg.norm(v, axis=-1),
        rtol=tol,
        atol=tol,
    )
    angle = np.linalg.norm(np.asarray(other["log"], float), axis=-1)
    assert np.all(angle <= np.pi * (1 + 1e-6))
    np.testing.assert_allclose(
        np.asarray(other["R Rᵀ"], float), np.broadcast_to(np.eye(3), batch + (3, 3)), atol=tol
    )
    # eager calls as a user makes them, on the same numbers
    np.testing.assert_allclose(
        np.asarray(so3.exp(jnp.asarray(phi, dtype))), np.asarray(unit["exp"]), rtol=tol, atol=tol
    )


@fast_settings(20)
@given(st.data())
def test_boxplus_boxminus_finite_unit_and_shape_checked(data):
    """Moderate input: finite, unit ``q``, ``(x ⊞ δ) ⊟ x = δ`` for ``|dθ| < π``; a wrong
    ``delta`` size, field shape, batch or type raises ``ValueError``."""
    dtype = data.draw(st.sampled_from((np.float64, np.float32)), label="dtype")
    batch = data.draw(st.sampled_from(((), (2,), (0,))), label="batch")
    rng = rng_of(data)
    state = NavState(
        jnp.asarray(random_unit_quat(rng, batch, dtype)),
        *(jnp.asarray(rng.normal(0, 10, batch + (3,)), dtype) for _ in range(4)),
    )
    delta = rng.normal(0, 1, batch + (15,))
    delta[..., :3] *= 2.5 / max(1.0, np.linalg.norm(delta[..., :3], axis=-1).max(initial=0.0))
    fault = data.draw(
        st.sampled_from((None, None, None, "delta", "state", "batch", "type")), label="fault"
    )
    if fault is None:
        moved = jaximu.boxplus(state, jnp.asarray(delta, dtype))
        assert_unit(moved.q, dtype)
        assert_finite(moved)
        back = jaximu.boxminus(moved, state)
        np.testing.assert_allclose(
            np.asarray(back, float), delta, atol=2e-3 if dtype == np.float32 else 1e-9
        )
        return
    with pytest.raises(ValueError) as err:
        if fault == "delta":
            jaximu.boxplus(state, delta[..., :14])
        elif fault == "state":
            jaximu.boxminus(state.replace(p=state.p[..., :2]), state)
        elif fault == "batch":  # batch (2,) against (5,)
            if data.draw(st.booleans(), label="boxminus"):
                jaximu.boxminus(NavState.identity((2,), dtype), NavState.identity((5,), dtype))
            else:
                jaximu.boxplus(NavState.identity((2,), dtype), np.zeros((5, 15), dtype))
        else:
            jaximu.boxplus((state.q, state.p), delta)
    pattern = {
        "delta": r"delta must have shape \(\.\.\., 15\)",
        "state": r"state\.p must have",
        "batch": "do not broadcast",
        "type": "state must be a jaximu.NavState",
    }[fault]
    assert re.search(pattern, str(err.value)), str(err.value)
