"""The whole-sequence evaluation's rows and where it compares: the tracker-alone row against
the model with its network's correction zeroed (another code path: the network's), and a
TUM-VI excerpt with a motion-capture dropout against scipy's ``Rotation`` integration at the
motion capture's own stamps, read from the file with numpy."""

from __future__ import annotations

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp
from test_learning_losses import make_sequence, scipy_attitudes

from jaximu import learning
from jaximu.learning import Denoiser, ModelConfig, evaluate_sequence
from jaximu.learning.model import without_network

TUMVI = pathlib.Path(__file__).parents[1] / "data" / "tumvi_room4" / "mav0"
SMALL = dict(channels=(4, 4), kernel=3, dilations=(1, 2), dropout=0.0)


def _with_random_head(model, key):
    """``model`` with a non-zero correction head and ``C`` (a trained network's stand-in)."""
    k1, k2, k3 = jax.random.split(key, 3)
    w = 0.3 * jax.random.normal(k1, model.head.weight.shape, jnp.float32)
    b = 0.3 * jax.random.normal(k2, model.head.bias.shape, jnp.float32)
    C = 0.01 * jax.random.normal(k3, (3, 3), jnp.float32)
    return eqx.tree_at(lambda m: (m.head.weight, m.head.bias, m.gyro_matrix), model, (w, b, C))


def test_tracker_alone_row_equals_the_model_with_its_correction_zeroed():
    rng = np.random.default_rng(5)
    seq, _ = make_sequence(rng, T=800)
    cfg = ModelConfig(**SMALL, gyro_bias=(0.01, -0.02, 0.015), update_samples=10)
    model = _with_random_head(Denoiser(cfg, jax.random.key(1)), jax.random.key(2))
    rep = evaluate_sequence(model, seq, dtype=jnp.float64)
    zeroed = evaluate_sequence(without_network(model), seq, dtype=jnp.float64)
    assert set(rep.metrics) == {"raw", "constant_bias", "tracker", "learned"}
    a, b = rep.metrics["tracker"], zeroed.metrics["learned"]
    np.testing.assert_allclose(
        [a.aoe_mean, a.aoe_rmse, a.aye_mean, a.aye_rmse],
        [b.aoe_mean, b.aoe_rmse, b.aye_mean, b.aye_rmse],
        rtol=1e-10,
    )
    np.testing.assert_allclose(rep.aoe["tracker"], zeroed.aoe["learned"], rtol=1e-9, atol=1e-12)
    # the head does change the learned row: the comparison is not vacuous
    assert abs(rep.metrics["learned"].aoe_mean - a.aoe_mean) > 1e-3 * a.aoe_mean
    # a model without the tracker has no tracker row (it would be the constant bias)
    plain = Denoiser(ModelConfig(**SMALL, bias_tracking=False), jax.random.key(1))
    assert "tracker" not in evaluate_sequence(plain, seq, dtype=jnp.float64).metrics


_TRACED: list = []  # the functions JAX traced (one per compile-cache miss), in order
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, fun_name=None, **_: (
        _TRACED.append(fun_name) if event == "/jax/core/compile/jaxpr_trace_duration" else None
    )
)


def test_recordings_of_about_one_length_share_the_evaluations_programs():
    """The whole-run evaluation, the dead-reckoning windows and the windowed NEES of a
    recording of 900 samples run the programs compiled for one of 800 (both padded to 1024
    samples): nothing is traced again, and the padding changes nothing the rows measure —
    the raw and learned rows against scipy's integration of the raw gyro and of the
    model's correction of the 900 samples alone, at every sample."""
    rng = np.random.default_rng(11)
    cfg = ModelConfig(**SMALL, gyro_bias=(0.01, -0.02, 0.015), update_samples=10)
    model = _with_random_head(Denoiser(cfg, jax.random.key(1)), jax.random.key(2))
    model = model.astype(jnp.float64)
    f64 = jnp.float64

    def run(seq):
        return (
            evaluate_sequence(model, seq, dtype=f64),
            learning.evaluation.window_errors(model, seq, 1.0, dtype=f64),
            learning.window_nees(model, seq, 1.0, dtype=f64),
        )

    run(make_sequence(rng, T=800)[0])
    seq, _ = make_sequence(rng, T=900)
    before = len(_TRACED)
    rep, _, nees = run(seq)
    assert _TRACED[before:] == [], f"traced again: {_TRACED[before:]}"
    assert np.isfinite(nees)
    truth = Rotation.from_quat(np.roll(seq.q, -1, axis=-1))
    corrected = np.asarray(model(jnp.asarray(seq.gyro), jnp.asarray(seq.accel)).gyro)
    for row, gyro in (("raw", seq.gyro), ("learned", corrected)):
        _, Rs = scipy_attitudes(seq.q[0], gyro, seq.dt[0])
        aoe = np.degrees((truth.inv() * Rotation.concatenate(Rs)).magnitude())
        assert len(rep.aoe[row]) == len(seq)
        np.testing.assert_allclose(rep.aoe[row], aoe, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(rep.metrics[row].aoe_mean, aoe.mean(), rtol=1e-7)


def _read(path):
    rows = np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64)
    stamps = np.loadtxt(path, delimiter=",", comments="#", usecols=0, dtype=np.int64)
    return stamps, rows[:, 1:]


def test_tumvi_excerpt_with_a_dropout_is_compared_only_at_motion_capture_stamps():
    """The excerpt's mocap drops frames (up to 0.483 s); its IMU intervals vary (4.995–5.036 ms).
    The raw gyro is integrated by scipy with each sample's own interval from the mocap's
    attitude slerped at the first IMU sample inside it, carried to every mocap stamp, and
    compared there: the evaluation's AOE/AYE are these, and no sample in the dropout has a
    reference."""
    imu_ns, imu = _read(TUMVI / "imu0" / "data.csv")
    gt_ns, gt = _read(TUMVI / "mocap0" / "data.csv")
    t0 = imu_ns[0]
    t = (imu_ns - t0) * 1e-9
    tau = (gt_ns - t0) * 1e-9
    first = int(np.searchsorted(t, tau[0]))
    last = int(np.searchsorted(t, tau[-1], side="right")) - 1
    t, gyro = t[first : last + 1], imu[first : last + 1, 0:3]
    R_gt = Rotation.from_quat(gt[:, [4, 5, 6, 3]])  # wxyz → scipy's xyzw
    R = Slerp(tau, R_gt)([t[0]])[0]
    Rs = [R]
    for w, h in zip(gyro[:-1], np.diff(t)):
        R = R * Rotation.from_rotvec(w * h)
        Rs.append(R)
    inside = (tau >= t[0]) & (tau <= t[-1])
    k = np.clip(np.searchsorted(t, tau[inside], side="right") - 1, 0, len(t) - 2)
    est = Rotation.concatenate(
        [Rs[j] * Rotation.from_rotvec(gyro[j] * (s - t[j])) for j, s in zip(k, tau[inside])]
    )
    ref = R_gt[inside]
    aoe = np.degrees((ref.inv() * est).magnitude())
    aye = np.degrees(np.abs((est * ref.inv()).as_euler("ZYX")[:, 0]))

    seq = learning.load_sequence(TUMVI.parent)
    gaps = np.diff(tau)
    assert gaps.max() > 0.48 and np.ptp(np.diff(t)) > 1.5e-5  # a dropout, uneven intervals
    # dropouts: intervals longer than 5 × the median (the default max_gap)
    drops = np.flatnonzero(gaps > 5 * np.median(gaps))
    in_dropout = np.zeros(len(t), bool)
    for j in drops:
        in_dropout |= (t > tau[j]) & (t < tau[j + 1])
    assert len(drops) >= 2 and in_dropout.sum() > 90
    np.testing.assert_array_equal(seq.has_reference, ~in_dropout)
    model = Denoiser(ModelConfig(**SMALL, bias_tracking=False), jax.random.key(0))
    rep = evaluate_sequence(model, seq, dtype=jnp.float64)
    assert len(rep.t) == inside.sum()  # every mocap stamp, none in the dropout
    np.testing.assert_allclose(rep.t, tau[inside] - t[0], atol=1e-12)
    m = rep.metrics["raw"]
    np.testing.assert_allclose(
        [m.aoe_mean, m.aoe_rmse, m.aye_mean, m.aye_rmse],
        [aoe.mean(), np.sqrt(np.mean(aoe**2)), aye.mean(), np.sqrt(np.mean(aye**2))],
        rtol=1e-7,
    )
    np.testing.assert_allclose(rep.aoe["raw"], aoe, rtol=1e-6, atol=1e-9)


def test_a_sequence_starting_in_a_dropout_is_refused_naming_the_fix():
    seq = learning.load_sequence(TUMVI.parent)
    start = int(np.argmin(seq.has_reference)) + 1
    model = Denoiser(ModelConfig(**SMALL, bias_tracking=False), jax.random.key(0))
    with pytest.raises(learning.data.DataError, match="starts inside a ground-truth gap"):
        evaluate_sequence(model, seq.slice(start))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(reference=np.ones(5, bool)), r"Sequence.reference must be \(10,\) booleans"),
        (dict(reference=np.ones(10)), r"Sequence.reference must be \(10,\) booleans"),
        (dict(gt_t=np.arange(3) * 0.1), "gt_t and Sequence.gt_q are given together"),
        (dict(gt_t=np.arange(3) * 0.1, gt_q=np.ones((2, 4))), r"gt_q \(M, 4\)"),
        (dict(gt_t=[0.0, 0.5, 0.9], gt_q=np.ones((3, 4))), r"inside \[t\[0\], t\[-1\]\]"),
        (dict(gt_t=[0.0, 0.2, 0.1], gt_q=np.ones((3, 4))), "increase strictly"),
        (dict(gt_t=[0.0, 0.1, 0.2], gt_q=np.ones((3, 4))), "gt_q must hold unit quaternions"),
    ],
)
def test_a_sequences_reference_and_stamps_are_checked_naming_the_field(kw, match):
    t = np.arange(10) * 0.05
    z, q = np.zeros((10, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    with pytest.raises(ValueError, match=match):
        learning.Sequence("s", t, z, z, q, z, z, **kw)
