"""Monte Carlo covariance studies: does the linearised covariance match the real spread?

For one true motion, N noisy IMU streams are drawn (white noise, bias random walk, an
initial-state error from ``P0``), each is propagated, and the errors are compared with the
covariance that :func:`jaximu.propagate_covariance` predicts. This is what GTSAM's
``ScenarioRunner::estimateCovariance`` does in a serial loop; here every chunk of runs is
one batched scan, chunks keep memory bounded (N = 10^6 is fine), and the run axis is
sharded over all JAX devices.

Chunk c draws its runs from the key ``fold_in(key, c)`` in one call (the fastest way on
CPU): the numbers depend on the key and the chunk size, not on the number of devices.
Each run:

* the estimator starts at ``x̂_0 = x_0 ⊞ ε``, ``ε ~ N(0, P0)``, and keeps its bias estimate;
* the true biases start at ``b_0`` and random-walk; the samples are the exact IMU signals of
  the trajectory plus biases plus white noise (:func:`jaximu.simulate.add_noise`);
* the error at a recorded time is ``e_k = x_k ⊟ x̂_k`` (15-dim), where ``x_k`` is the noise-free
  propagation of the exact signals from ``x_0`` with the true biases (GTSAM's convention: the
  scheme's discretisation error, reported apart as ``discretization_error``, does not enter
  the statistics);
* ``NEES_k = e_kᵀ P_k⁻¹ e_k``. If the covariance is right, its average over N runs is
  ``χ²(15N)/N``-distributed.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import _validation as val
from jaximu.errorstate import propagate_covariance
from jaximu.noise import ImuNoise
from jaximu.propagate import _propagate
from jaximu.simulate import Trajectory, add_noise, ideal_imu, true_states
from jaximu.state import NavState, boxminus, boxplus

__all__ = ["MonteCarloResult", "monte_carlo", "chi2_interval"]


class MonteCarloResult(NamedTuple):
    """Statistics of a Monte Carlo run (numpy arrays, float64; K recorded times).

    Attributes:
        times: ``(K,)`` recorded times [s].
        mean_error: ``(K, 15)`` mean of ``e_k`` over the runs.
        error_cov: ``(K, 15, 15)`` empirical covariance of ``e_k`` (N - 1 normalisation).
        predicted_cov: ``(K, 15, 15)`` the linearised covariance.
        nees: ``(N, K)`` NEES of every run at every recorded time.
        nees_mean: ``(K,)`` average NEES over the runs.
        nees_bounds: ``(2,)`` the two-sided interval of the average NEES at ``confidence``.
        sample_errors: ``(n_keep, K, 15)`` the errors of the first runs (for plots).
        discretization_error: ``(K, 15)`` noise-free propagation ⊟ true trajectory.
        n_runs: N.
        confidence: the interval's confidence.
    """

    times: np.ndarray
    mean_error: np.ndarray
    error_cov: np.ndarray
    predicted_cov: np.ndarray
    nees: np.ndarray
    nees_mean: np.ndarray
    nees_bounds: np.ndarray
    sample_errors: np.ndarray
    discretization_error: np.ndarray
    n_runs: int
    confidence: float

    @property
    def consistent(self) -> np.ndarray:
        """``(K,)``: whether the average NEES lies inside its interval at each time."""
        return (self.nees_mean >= self.nees_bounds[0]) & (self.nees_mean <= self.nees_bounds[1])


def chi2_interval(dof, confidence: float = 0.95):
    """Two-sided interval of a ``χ²(dof)`` variable by the Wilson-Hilferty approximation
    (no scipy needed). Relative error at 99%: 1.2% at dof 15, 2e-4 at 150, 5e-6 at 1500,
    5e-8 at 30000 (the average NEES of N runs has dof 15 N). ``dof > 0``; ``confidence``
    in ``(0, 1)`` (0.95, not 95). Returns ``(lo, hi)``."""
    from jax.scipy.special import ndtri

    k = val.check_positive("dof", dof)
    confidence = val.check_fraction("confidence", confidence)
    z = float(ndtri(0.5 + confidence / 2))
    c = 2.0 / (9.0 * k)
    return (k * (1 - c - z * math.sqrt(c)) ** 3, k * (1 - c + z * math.sqrt(c)) ** 3)


def _progress(total, enabled):
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, unit="run", desc="Monte Carlo")


@functools.partial(jax.jit, static_argnames=("scheme", "rec"))
def _chunk_stats(key, valid, c, *, scheme, rec):
    """One chunk of runs (the chunk size is ``valid``'s length; its sharding is followed)."""
    n = valid.shape[0]
    dtype = c["dt"].dtype
    k_init, k_noise = jax.random.split(key)
    eps = jax.random.normal(k_init, (n, 15), dtype) @ c["L0"].T
    dt_samples = jnp.concatenate([c["dt"], c["dt"][-1:]])
    w_m, a_m, err = add_noise(k_noise, c["gyro"], c["accel"], dt_samples, c["noise"],
                              b_g0=c["b_g0"], b_a0=c["b_a0"], batch_shape=(n,))
    x0 = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), c["x0"])
    start = boxplus(x0, eps)
    rec_j = jnp.asarray(rec)
    if len(rec) <= 16:  # propagate segment by segment, keeping only the recorded states
        q, p, v, parts = start.q, start.p, start.v, []
        lo = 0
        for r in rec:  # steps lo..r; midpoint/RK4 also read sample r+1 (interval form)
            hi = r + 1 if scheme == "euler" else r + 2
            s = _propagate(start.replace(q=q, p=p, v=v), w_m[:, lo:hi], a_m[:, lo:hi],
                           c["dt"][lo:r + 1], c["g"], scheme=scheme, attitude="quaternion",
                           save_all=False)[0]
            q, p, v = s.q, s.p, s.v
            parts.append((q, p, v))
            lo = r + 1
        est_q, est_p, est_v = (jnp.stack([x[i] for x in parts], 1) for i in range(3))
    else:
        est = _propagate(start, w_m, a_m, c["dt"], c["g"], scheme=scheme, attitude="quaternion",
                         save_all=True)[0]
        est_q, est_p, est_v = est.q[:, rec_j], est.p[:, rec_j], est.v[:, rec_j]
    K = len(rec)
    est = NavState(est_q, est_p, est_v, jnp.broadcast_to(start.b_g[:, None], (n, K, 3)),
                   jnp.broadcast_to(start.b_a[:, None], (n, K, 3)))
    # the truth: the clean propagation, with the true biases after each step
    walk_g = jnp.concatenate([err.b_g[:, 1:], err.b_g_end[:, None]], 1)[:, rec_j]
    walk_a = jnp.concatenate([err.b_a[:, 1:], err.b_a_end[:, None]], 1)[:, rec_j]
    ref = NavState(c["ref"].q, c["ref"].p, c["ref"].v, walk_g, walk_a)
    e = boxminus(ref, est)  # (n, K, 15)
    nees = jnp.einsum("nki,kij,nkj->nk", e, c["P_inv"], e)
    w = valid.astype(dtype)[:, None, None]
    return jnp.sum(e * w, 0), jnp.einsum("nki,nkj->kij", e * w, e), nees, e


def monte_carlo(trajectory: Trajectory, times, P0, noise: ImuNoise, n_runs: int, key, *,
                scheme: str = "euler", gravity=9.81, b_g0=None, b_a0=None,
                record_every: int = 1, chunk_size: int = 1024, n_keep: int = 100,
                confidence: float = 0.95, progress: bool = False, shard: bool = True,
                dtype=None) -> MonteCarloResult:
    """Monte Carlo covariance study of ``n_runs`` noisy copies of one trajectory.

    Args:
        trajectory: the true motion, a :class:`jaximu.simulate.Trajectory`.
        times: ``(T+1,)`` sample times [s], finite and strictly increasing, at least 2; T
            steps (the samples are the interval ends).
        P0: ``(15, 15)`` initial error covariance ``[dθ, dp, dv, db_g, db_a]``, symmetric
            positive semi-definite (judged relative to its scale, as
            :func:`jaximu.propagate_covariance`).
        noise: the :class:`ImuNoise` densities used both to draw the noise and to predict the
            covariance. (To test a filter's noise model, draw with one and predict with
            another: pass ``noise=(draw, predict)``.)
        n_runs: N, an integer ≥ 2.
        key: a ``jax.random`` key.
        scheme: the propagation scheme of the estimator (``"euler"``, ``"midpoint"``,
            ``"rk4"``).
        gravity: magnitude ``g ≥ 0`` [m/s²] (``g_W = [0, 0, -g]``) or a ``(3,)`` vector.
        b_g0, b_a0: true turn-on biases ``(3,)`` [rad/s], [m/s²], finite (default zero).
        record_every: record errors every this many steps (and at the last); an integer ≥ 1.
        chunk_size: runs per batched call, an integer ≥ 1 (memory: ``chunk × T × 16``
            floats).
        n_keep: runs whose errors are returned in ``sample_errors``, an integer ≥ 0.
        confidence: the NEES interval's probability, in ``(0, 1)`` (0.95, not 95).
        progress: show a progress bar (needs ``tqdm``).
        shard: split each chunk's runs over all JAX devices (``jax.sharding``).
        dtype: computation dtype, float32 or float64 (float64 needs ``jax_enable_x64``;
            default: float64 if enabled, else float32).

    Returns:
        :class:`MonteCarloResult`.

    Raises:
        ValueError: naming the argument, for any of them outside the domain above.
    """
    from jaximu.errorstate import _check_cov
    from jaximu.integrators import SCHEMES

    if not isinstance(trajectory, Trajectory):
        raise ValueError("trajectory must be a jaximu.simulate.Trajectory (e.g. "
                         f"jaximu.simulate.circle()), got {type(trajectory).__name__}")
    if isinstance(noise, tuple):
        if len(noise) != 2:
            raise ValueError("noise must be an ImuNoise or a pair (draw, predict) of them, got a "
                             f"tuple of {len(noise)}")
        draw_noise, model_noise = noise
    else:
        draw_noise = model_noise = noise
    n_runs = val.check_int("n_runs", n_runs, 2)
    record_every = val.check_int("record_every", record_every, 1)
    chunk_size = val.check_int("chunk_size", chunk_size, 1)
    n_keep = val.check_int("n_keep", n_keep, 0)
    confidence = val.check_fraction("confidence", confidence)
    val.check_choice("scheme", scheme, SCHEMES)
    dtype = val.compute_dtype("dtype", dtype) if dtype is not None else jnp.result_type(float)
    times = np.asarray(times, np.float64)
    if times.ndim != 1 or len(times) < 2:
        raise ValueError(f"times must be a 1-D array of at least 2 sample times, got shape "
                         f"{times.shape}")
    val.check_finite("times", times)
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0))
        raise ValueError(f"times must increase strictly; times[{i + 1}] = {times[i + 1]:g} ≤ "
                         f"times[{i}] = {times[i]:g}")
    P0 = np.asarray(P0, np.float64)
    if P0.shape != (15, 15):
        raise ValueError(f"P0 must have shape (15, 15), got {P0.shape}")
    _check_cov(P0, np.float64)
    lam, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    L0 = jnp.asarray(V * np.sqrt(np.clip(lam, 0, None)), dtype)  # L0 L0ᵀ = P0, also if singular
    model_noise = val.check_noise(model_noise, dtype)
    draw_noise = val.check_noise(draw_noise, dtype)
    g = val.gravity_vector(gravity, dtype)
    if g.ndim != 1:
        raise ValueError(f"gravity must be a magnitude or a (3,) vector, got shape {g.shape}")
    b_g0 = np.zeros(3) if b_g0 is None else val.check_array("b_g0", b_g0, (3,))
    b_a0 = np.zeros(3) if b_a0 is None else val.check_array("b_a0", b_a0, (3,))
    T = len(times) - 1
    dt = jnp.asarray(np.diff(times), dtype)
    t = jnp.asarray(times, dtype)
    gyro, accel = ideal_imu(trajectory, t, gravity)
    truth = true_states(trajectory, t)
    b_g0 = jnp.asarray(b_g0, dtype)
    b_a0 = jnp.asarray(b_a0, dtype)
    x0 = NavState(truth.q[0], truth.p[0], truth.v[0], b_g0, b_a0)
    rec = np.unique(np.r_[np.arange(record_every - 1, T, record_every), T - 1])
    rec_j = jnp.asarray(rec)

    # The reference: noise-free propagation of the exact signals (with the true biases added
    # to the samples and to the state, which cancel), and the linearised covariance.
    clean = _propagate(x0, gyro + b_g0, accel + b_a0, dt, g, scheme=scheme,
                       attitude="quaternion", save_all=True)[0]
    _, P = propagate_covariance(x0, P0.astype(dtype), gyro + b_g0, accel + b_a0, dt,
                                model_noise, scheme)
    P_rec = np.asarray(P, np.float64)[rec]
    P_inv = jnp.asarray(np.linalg.inv(P_rec), dtype)
    truth_rec = jax.tree_util.tree_map(lambda x: x[rec_j + 1], truth)
    clean_rec = jax.tree_util.tree_map(lambda x: x[rec_j], clean)
    disc = np.asarray(boxminus(clean_rec, truth_rec.replace(b_g=clean_rec.b_g, b_a=clean_rec.b_a)),
                      np.float64)

    consts = dict(x0=x0, L0=L0, gyro=gyro, accel=accel, dt=dt, g=g, noise=draw_noise,
                  ref=clean_rec, P_inv=P_inv, b_g0=b_g0, b_a0=b_a0)
    devices = jax.devices() if shard else jax.devices()[:1]
    n_dev = len(devices)
    chunk = max(n_dev, (min(chunk_size, n_runs) + n_dev - 1) // n_dev * n_dev)
    sharding = None
    if n_dev > 1:
        mesh = jax.sharding.Mesh(np.asarray(devices), ("runs",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("runs"))

    K = len(rec)
    s1 = np.zeros((K, 15))
    s2 = np.zeros((K, 15, 15))
    nees_all = np.zeros((n_runs, K))
    keep = np.zeros((min(n_keep, n_runs), K, 15))
    bar = _progress(n_runs, progress)
    for start in range(0, n_runs, chunk):
        valid = np.arange(start, start + chunk) < n_runs
        valid_j = jnp.asarray(valid)
        if sharding is not None:
            valid_j = jax.device_put(valid_j, sharding)
        a, b, nees, e = _chunk_stats(jax.random.fold_in(key, start // chunk), valid_j, consts,
                                     scheme=scheme, rec=tuple(int(r) for r in rec))
        s1 += np.asarray(a, np.float64)
        s2 += np.asarray(b, np.float64)
        n_valid = int(valid.sum())
        nees_all[start:start + n_valid] = np.asarray(nees, np.float64)[:n_valid]
        if start < len(keep):
            m = min(len(keep) - start, n_valid)
            keep[start:start + m] = np.asarray(e, np.float64)[:m]
        if bar is not None:
            bar.update(n_valid)
    if bar is not None:
        bar.close()
    mean = s1 / n_runs
    cov = (s2 - n_runs * np.einsum("ki,kj->kij", mean, mean)) / (n_runs - 1)
    lo, hi = chi2_interval(15 * n_runs, confidence)
    return MonteCarloResult(
        times=times[rec + 1], mean_error=mean, error_cov=cov, predicted_cov=P_rec,
        nees=nees_all, nees_mean=nees_all.mean(axis=0), nees_bounds=np.array([lo, hi]) / n_runs,
        sample_errors=keep, discretization_error=disc, n_runs=n_runs, confidence=confidence)
