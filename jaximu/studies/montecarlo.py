"""Monte Carlo covariance studies: does the linearised covariance match the real spread?

For one true motion, N noisy IMU streams are drawn (white noise, bias random walk, an
initial-state error from ``P0``), each is propagated, and the errors are compared with the
covariance that :func:`jaximu.propagate_covariance` predicts. This is what GTSAM's
``ScenarioRunner::estimateCovariance`` does in a serial loop; here the runs are the lanes
of one structure-of-arrays scan (:mod:`jaximu.kernels.soa`), and the noise is drawn inside the
scan step from a counter-based generator (:mod:`jaximu.kernels.rng`):

* the numbers of run ``i`` at step ``k`` are a pure function of ``(key, stream, i, k)``: no
  ``(runs, T, 12)`` array is formed, the result does not depend on the chunk size, on the
  devices or on the number of processes (to rounding of the sums), and
  :func:`sample_run` regenerates any single run alone;
* statistics stream: per chunk of runs, the mean and centred second moment of the errors
  at each recorded time are reduced on the device and combined on the host in float64
  (Chan et al.'s pairwise update); the memory does not grow with ``n_runs`` (the per-run
  NEES is kept only on request, ``keep_nees=True``);
* chunks are spread over all local devices (one chunk in flight per device) and, under
  ``jax.distributed``, over processes (process ``p`` of ``P`` runs chunks ``p, p + P, …``);
  the statistics are combined across processes and every process returns the same result.

Each run:

* the estimator starts at ``x̂_0 = x_0 ⊞ ε``, ``ε ~ N(0, P0)``, and keeps its bias estimate;
* the true biases start at ``b_0`` and random-walk; the samples are the exact IMU signals of
  the trajectory plus biases plus white noise (the model of :func:`jaximu.simulate.add_noise`:
  sample ``j`` carries white noise ``σ/√dt_j · n`` and the bias after the walk steps before
  ``j``);
* the error at a recorded time is ``e_k = x_k ⊟ x̂_k`` (15-dim), where ``x_k`` is the noise-free
  propagation of the exact signals from ``x_0`` with the true biases (GTSAM's convention: the
  scheme's discretisation error, reported apart as ``discretization_error``, does not enter
  the statistics);
* ``NEES_k = e_kᵀ P_k⁻¹ e_k``. If the covariance is right, its average over N runs is
  ``χ²(15N)/N``-distributed.

With ``update_every`` the study is a filter's (:func:`jaximu.errorstate.ekf_update`): every
run also propagates its own covariance, and every ``update_every`` steps it takes a
measurement (a position fix, :class:`PositionFix`) with its own noise and corrects its state
(error-state EKF, Joseph form). The NEES is then against each run's own covariance and the
NIS (``νᵀ S⁻¹ ν``, dof ``m``) is reported too.
"""

from __future__ import annotations

import concurrent.futures
import json
import math
import os
import pathlib
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine.errorstate import _check_cov, propagate_covariance
from jaximu.engine.propagate import _propagate
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import NavState, boxminus
from jaximu.kernels import rng as _rng
from jaximu.kernels.montecarlo_lanes import _N_STREAMS, _chunk, _measured
from jaximu.schemes.integrators import SCHEME_OBJECTS, SCHEMES
from jaximu.studies._montecarlo_stats import _Acc, _allgather_f64, _Progress
from jaximu.studies.simulate import Trajectory, ideal_imu, true_states

__all__ = ["MonteCarloResult", "PositionFix", "monte_carlo", "sample_run", "chi2_interval",
           "load_result"]



class PositionFix(NamedTuple):
    """A position measurement ``z = p + ν``, ``ν ~ N(0, R)``, for the filter study.

    Attributes:
        sigma: standard deviation of each axis [m], a scalar or ``(3,)``, ``> 0``.
    """
    sigma: float | tuple = 0.1


class MonteCarloResult(NamedTuple):
    """Statistics of a Monte Carlo study (numpy arrays, float64; K recorded times).

    Attributes:
        times: ``(K,)`` recorded times [s].
        mean_error: ``(K, 15)`` mean of ``e_k`` over the runs.
        error_cov: ``(K, 15, 15)`` empirical covariance of ``e_k`` (N - 1 normalisation).
        predicted_cov: ``(K, 15, 15)`` open loop: the linearised covariance; filter study:
            the average over the runs of each run's own covariance after the update.
        nees: ``(N, K)`` NEES of every run at every recorded time with ``keep_nees=True``,
            else ``None`` (memory ``N·K``); NaN where the NEES is undefined (below).
        nees_mean: ``(K,)`` average NEES over the runs. NaN at a recorded time where the
            covariance is singular to the precision of the computation dtype
            (:func:`jaximu.geometry._tolerances.definiteness`; the filter study's judged on the runs'
            average): ``eᵀ P⁻¹ e`` is undefined there, e.g. in the first steps from an
            exactly known start (``P0 = 0``), where one step's position and velocity errors
            are the same accelerometer noise (:attr:`nees_defined`).
        nees_bounds: ``(2,)`` the two-sided interval of the average NEES at ``confidence``.
        sample_errors: ``(n_keep, K, 15)`` the errors of the first runs (for plots).
        discretization_error: ``(K, 15)`` noise-free propagation ⊟ true trajectory.
        n_runs: N.
        confidence: the interval's confidence.
        nees_hist: ``(H, nbins)`` counts of the per-run NEES at the recorded times
            ``nees_hist_index`` (values past the last edge in the last bin; NaN where the
            NEES is undefined).
        nees_hist_edges: ``(nbins + 1,)`` the bins' edges.
        nees_hist_index: ``(H,)`` indices into ``times`` of the histograms.
        nis_mean: filter study: ``(K,)`` average NIS at the updates (else ``None``).
        nis_bounds: filter study: ``(2,)`` its interval (dof ``m N``), else ``None``.
        settings: the options that produced the result (a dict; JSON-serialisable).
    """
    times: np.ndarray
    mean_error: np.ndarray
    error_cov: np.ndarray
    predicted_cov: np.ndarray
    nees: np.ndarray | None
    nees_mean: np.ndarray
    nees_bounds: np.ndarray
    sample_errors: np.ndarray
    discretization_error: np.ndarray
    n_runs: int
    confidence: float
    nees_hist: np.ndarray | None = None
    nees_hist_edges: np.ndarray | None = None
    nees_hist_index: np.ndarray | None = None
    nis_mean: np.ndarray | None = None
    nis_bounds: np.ndarray | None = None
    settings: dict | None = None

    @property
    def consistent(self) -> np.ndarray:
        """``(K,)``: whether the average NEES lies inside its interval at each time (False
        where it is undefined: :attr:`nees_defined`)."""
        return (self.nees_mean >= self.nees_bounds[0]) & (self.nees_mean <= self.nees_bounds[1])

    @property
    def nees_defined(self) -> np.ndarray:
        """``(K,)``: whether the NEES is defined at each recorded time (the covariance there
        is positive definite to the computation dtype's precision; see ``nees_mean``)."""
        return np.isfinite(self.nees_mean)

    def save(self, path) -> None:
        """Write the result (and its settings, as JSON) to ``path``, an ``.npz`` file in an
        existing folder (:func:`load_result` reads it back). A path without the ``.npz``
        suffix is refused (numpy would silently write ``path + ".npz"``)."""
        p = _result_path(path)
        if p.suffix.lower() != ".npz":
            raise InputError(f"path {str(p)!r} must end in .npz (numpy would write "
                             f"{str(p) + '.npz'!r} instead)", [Fix("path", str(p) + ".npz")])
        if p.is_dir():
            raise ValueError(f"path {str(p)!r} is a folder; name an .npz file in it")
        if not p.parent.is_dir():
            raise ValueError(f"path {str(p)!r}: the folder {str(p.parent)!r} does not exist")
        arrays: dict[str, Any] = {k: np.asarray(v) for k, v in self._asdict().items()
                  if v is not None and k not in ("settings", "n_runs", "confidence")}
        meta = dict(settings=self.settings or {}, n_runs=self.n_runs, confidence=self.confidence,
                    format=_FORMAT)
        arrays["__meta__"] = np.asarray(json.dumps(meta))
        np.savez(p, **arrays)


_FORMAT = "jaximu.montecarlo/1"
_REQUIRED = ("times", "mean_error", "error_cov", "predicted_cov", "nees_mean", "nees_bounds",
             "sample_errors", "discretization_error")


def _result_path(path) -> pathlib.Path:
    try:
        return pathlib.Path(path)
    except TypeError:
        raise ValueError(f"path must be a file name (str or os.PathLike), got "
                         f"{type(path).__name__}") from None


def load_result(path) -> MonteCarloResult:
    """Read a result written by :meth:`MonteCarloResult.save`. ``path``: that ``.npz`` file;
    a missing file, a folder, another kind of file, another ``.npz`` or a damaged result
    raise an error naming the file (``FileNotFoundError`` or ``ValueError``)."""
    import zipfile

    p = _result_path(path)
    if p.is_dir():
        raise ValueError(f"path {str(p)!r} is a folder, not a result file (.npz)")
    if not p.is_file():
        raise FileNotFoundError(f"path {str(p)!r}: no such file (a result written by "
                                "MonteCarloResult.save)")
    not_ours = (f"{str(p)!r} is not a jaximu Monte Carlo result (written by "
                "MonteCarloResult.save)")
    if not zipfile.is_zipfile(p):
        raise ValueError(f"{not_ours}: not an .npz archive")
    with np.load(p, allow_pickle=False) as f:
        if "__meta__" not in f.files:
            raise ValueError(f"{not_ours}: it holds the arrays {sorted(f.files)[:8]} and no "
                             "format tag")
        try:
            meta = json.loads(str(f["__meta__"]))
            fmt = meta.get("format")
        except (ValueError, AttributeError):
            raise ValueError(f"{not_ours}: its __meta__ is not the JSON settings") from None
        if fmt != _FORMAT:
            raise ValueError(f"{not_ours}: its format tag is {fmt!r}, this version reads "
                             f"{_FORMAT!r}")
        fields = {k: f[k] for k in f.files if k != "__meta__"}
    missing = [k for k in _REQUIRED if k not in fields]
    absent = [k for k in ("n_runs", "confidence") if k not in meta]
    if missing or absent:
        raise ValueError(f"{str(p)!r} is a damaged Monte Carlo result: "
                         f"{', '.join(missing + absent)} missing")
    stats: dict[str, Any] = {k: fields.get(k) for k in MonteCarloResult._fields
                             if k not in ("settings", "n_runs", "confidence")}
    return MonteCarloResult(**stats,
                            n_runs=int(meta["n_runs"]), confidence=float(meta["confidence"]),
                            settings=meta.get("settings"))


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


# --------------------------------------------------------------------------- set-up


class _Study(NamedTuple):
    consts: dict  # device constants of the kernel
    scheme: str
    seg: tuple
    rec: np.ndarray  # recorded step indices
    times: np.ndarray
    P_rec: np.ndarray | None  # open loop: the linearised covariance at the recorded times
    disc: np.ndarray
    dtype: object
    filt: bool


def _prepare(trajectory, times, P0, noise, key, *, scheme, gravity, b_g0, b_a0, record_every,
             dtype, update_every=None, measurement=None, nees=True):
    """Validate the inputs and build the kernel's constants (shared by :func:`monte_carlo`
    and :func:`sample_run`). ``nees``: refuse an open-loop study whose NEES is undefined at
    every recorded time (a single run's errors do not need it)."""
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
    record_every = val.check_int("record_every", record_every, 1)
    filt = update_every is not None
    if filt:
        record_every = val.check_int("update_every", update_every, 1)
        measurement = PositionFix() if measurement is None else measurement
        if not isinstance(measurement, PositionFix):
            raise ValueError("measurement must be a jaximu.montecarlo.PositionFix, got "
                             f"{type(measurement).__name__}")
        sigma = val.as_numbers("measurement.sigma", measurement.sigma)
        meas_sd = np.broadcast_to(sigma, (3,)) if sigma.ndim == 0 else sigma
        if meas_sd.shape != (3,) or not np.all(np.isfinite(meas_sd) & (meas_sd > 0)):
            raise ValueError(f"measurement.sigma must be positive and finite, a scalar or (3,), "
                             f"got {measurement.sigma!r}")
    elif measurement is not None:
        raise InputError("measurement is used only by the filter study, and update_every is "
                         "None (open loop): it would be ignored",
                         [Fix("update_every", phrase="{}=N (a measurement every N steps)"),
                          Fix("measurement", None)])
    val.check_choice("scheme", scheme, SCHEMES)
    dtype = val.compute_dtype("dtype", dtype) if dtype is not None else jnp.result_type(float)
    times = val.as_numbers("times", times)
    if times.ndim != 1 or len(times) < 2:
        raise ValueError(f"times must be a 1-D array of at least 2 sample times, got shape "
                         f"{times.shape}")
    val.check_finite("times", times)
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0))
        raise ValueError(f"times must increase strictly; times[{i + 1}] = {times[i + 1]:g} ≤ "
                         f"times[{i}] = {times[i]:g}")
    if filt and record_every > len(times) - 1:
        raise InputError(f"update_every = {record_every} is more than the {len(times) - 1} "
                         "steps of times: no update would happen", [
                             Fix("update_every", len(times) - 1, "")],
                         lead="pass at most")
    P0 = val.as_numbers("P0", P0)
    if P0.shape != (15, 15):
        raise ValueError(f"P0 must have shape (15, 15), got {P0.shape}")
    _check_cov(P0, dtype)
    lam, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    L0 = V * np.sqrt(np.clip(lam, 0, None))  # L0 L0ᵀ = P0, also if singular
    model_noise = check_noise(model_noise, dtype)
    draw_noise = check_noise(draw_noise, dtype)
    val.check_unbatched_noise(model_noise, "a Monte Carlo study")
    val.check_unbatched_noise(draw_noise, "a Monte Carlo study")
    g = val.gravity_vector(gravity, dtype)
    if g.ndim != 1:
        raise ValueError(f"gravity must be a magnitude or a (3,) vector, got shape {g.shape}")
    b_g0 = np.zeros(3) if b_g0 is None else val.check_array("b_g0", b_g0, (3,))
    b_a0 = np.zeros(3) if b_a0 is None else val.check_array("b_a0", b_a0, (3,))
    keys = _rng.stream_keys(key, _N_STREAMS)
    T = len(times) - 1
    dt64 = np.diff(times)
    dt = jnp.asarray(dt64, dtype)
    t = jnp.asarray(times, dtype)
    gyro, accel = ideal_imu(trajectory, t, gravity)
    truth = true_states(trajectory, t)
    b_g0 = jnp.asarray(b_g0, dtype)
    b_a0 = jnp.asarray(b_a0, dtype)
    x0 = NavState(truth.q[0], truth.p[0], truth.v[0], b_g0, b_a0)
    rec = np.unique(np.r_[np.arange(record_every - 1, T, record_every), T - 1])
    n_seg = T // record_every
    seg = (record_every, n_seg, T - n_seg * record_every)
    rec_j = jnp.asarray(rec)

    # The reference: noise-free propagation of the exact signals (with the true biases added
    # to the samples and to the state, which cancel), and (open loop) the linearised
    # covariance; the filter study's runs carry their own.
    clean = _propagate(x0, gyro + b_g0, accel + b_a0, dt, g, scheme=scheme,
                       attitude="quaternion", save_all=True)[0]
    P_rec = W = None
    if not filt:
        _, P = propagate_covariance(x0, jnp.asarray(P0, dtype), gyro + b_g0, accel + b_a0, dt,
                                    model_noise, scheme)
        P_rec = np.asarray(P, np.float64)[rec]
        # NEES = |W e|², W = L⁻¹, P = L Lᵀ, where P is positive definite to the dtype's
        # precision; elsewhere the NEES is undefined (NaN in the result, W = 0 meanwhile)
        defined = _tolerances.definiteness(P_rec, dtype)[0]
        if nees and not defined.any():
            k = len(rec) - 1
            _tolerances.check_definite(
                f"the predicted covariance at times[{rec[k] + 1}] = {times[rec[k] + 1]:g} "
                "(and at every recorded time)", P_rec[k], dtype, axes=_tolerances.ERROR_AXES,
                what="the NEES eᵀ P⁻¹ e, undefined at every recorded time",
                fix="P0 with the noise leaves some error direction without variance for the "
                    "whole study; give P0 positive variances on every axis (e.g. P0 = "
                    "diag(σ²), σ > 0), or the noise positive random walks")
        W = np.zeros_like(P_rec)
        W[defined] = np.linalg.inv(np.linalg.cholesky(P_rec[defined]))
        W = jnp.asarray(W, dtype)
    truth_rec = jax.tree_util.tree_map(lambda x: x[rec_j + 1], truth)
    clean_rec = jax.tree_util.tree_map(lambda x: x[rec_j], clean)
    disc = np.asarray(boxminus(clean_rec, truth_rec.replace(b_g=clean_rec.b_g, b_a=clean_rec.b_a)),
                      np.float64)

    # per-sample white-noise std (sample j held over dt_j; the last sample over dt_{T-1}) and
    # per-step bias-walk std, in float64 then rounded once
    sg, sa, sbg, sba = (np.broadcast_to(np.asarray(x, np.float64), (3,)) if np.ndim(x) == 0
                        else np.asarray(x, np.float64) for x in (
                            draw_noise.gyroscope_noise_density,
                            draw_noise.accelerometer_noise_density,
                            draw_noise.gyroscope_random_walk,
                            draw_noise.accelerometer_random_walk))
    dt_s = np.r_[dt64, dt64[-1]]
    sd = np.concatenate([sg, sa])[None] / np.sqrt(dt_s)[:, None]  # (T+1, 6)
    sw = np.concatenate([sbg, sba])[None] * np.sqrt(dt64)[:, None]  # (T, 6)
    nxt = SCHEME_OBJECTS[scheme].uses_next_sample
    sl = slice(1, None) if nxt else slice(0, T)  # the sample each step draws
    consts = dict(keys=keys, L0=jnp.asarray(L0, dtype), x0=x0.replace(b_g=b_g0 * 0, b_a=b_a0 * 0),
                  dt=dt, g=g, w_in=gyro[sl], a_in=accel[sl], sd_in=jnp.asarray(sd[sl], dtype),
                  w0=gyro[0], a0=accel[0], sd0=jnp.asarray(sd[0], dtype),
                  sw=jnp.asarray(sw, dtype), ref=(clean_rec.q, clean_rec.p, clean_rec.v),
                  W=W, gyro=gyro, accel=accel, sd=jnp.asarray(sd, dtype),
                  b0=jnp.concatenate([b_g0, b_a0]))
    if filt:
        consts.update(qc=model_noise.discrete_variances(dt), P0=jnp.asarray(P0, dtype),
                      meas_sd=jnp.asarray(meas_sd, dtype),
                      meas_R=jnp.asarray(np.diag(meas_sd**2), dtype))
    return _Study(consts, scheme, seg, rec, times[rec + 1], P_rec, disc, dtype, filt)


# --------------------------------------------------------------------------- the study


def monte_carlo(trajectory: Trajectory, times, P0, noise: ImuNoise, n_runs: int, key, *,
                scheme: str = "euler", gravity=9.81, b_g0=None, b_a0=None,
                record_every: int = 1, chunk_size: int = 2048, n_keep: int = 100,
                confidence: float = 0.95, progress: bool = False, shard: bool = True,
                dtype=None, keep_nees: bool = False, nees_hist_times=(-1,),
                nees_bins=None, update_every: int | None = None,
                measurement: PositionFix | None = None) -> MonteCarloResult:
    """Monte Carlo covariance study of ``n_runs`` noisy copies of one trajectory.

    Args:
        trajectory: the true motion, a :class:`jaximu.simulate.Trajectory`.
        times: ``(T+1,)`` sample times [s], finite and strictly increasing, at least 2; T
            steps (the samples are the interval ends).
        P0: ``(15, 15)`` initial error covariance ``[dθ, dp, dv, db_g, db_a]``, symmetric
            positive semi-definite (judged relative to its scale, as
            :func:`jaximu.propagate_covariance`). A singular ``P0`` is allowed (``0``: an
            exactly known start): the NEES is NaN at the recorded times where the predicted
            covariance is still singular (``MonteCarloResult.nees_mean``); an open-loop
            study where it is singular at every recorded time is refused before the work
            (``ValueError`` naming the axes without variance).
        noise: the :class:`ImuNoise` densities (scalars or ``(3,)``) used both to draw the
            noise and to predict the covariance. (To test a filter's noise model, draw with
            one and predict with another: pass ``noise=(draw, predict)``.)
        n_runs: N, an integer from 2 to 2³².
        key: a ``jax.random`` key (threefry, the default). Run ``i`` is a function of
            ``(key, i)`` only: :func:`sample_run` regenerates it.
        scheme: the propagation scheme of the estimator (``"euler"``, ``"midpoint"``,
            ``"rk4"``).
        gravity: magnitude ``g ≥ 0`` [m/s²] (``g_W = [0, 0, -g]``) or a ``(3,)`` vector.
        b_g0, b_a0: true turn-on biases ``(3,)`` [rad/s], [m/s²], finite (default zero).
        record_every: record errors every this many steps (and at the last); an integer ≥ 1.
        chunk_size: the most runs per device call (the lanes of one scan), an integer ≥ 1;
            memory ``O(chunk · K)``, independent of ``n_runs``. Chunks are made as even as
            the chunks in flight allow (``_chunk_runs``: no half-idle last round). The
            statistics do not depend on it (to the rounding of the sums). A chunk of one
            run is computed beside an idle lane (a one-lane program rounds differently:
            ``_lane_errors``).
        n_keep: runs whose errors are returned in ``sample_errors``, an integer ≥ 0 (the
            first ``min(n_keep, n_runs)``).
        confidence: the NEES interval's probability, in ``(0, 1)`` (0.95, not 95).
        progress: bool, show progress (runs/s and ETA; a ``tqdm`` bar when installed).
        shard: bool, spread the chunks over all local JAX devices (one in flight per device;
            on a CPU device, one per core the process may use, each from its own thread).
        dtype: computation dtype, float32 or float64 (float64 needs ``jax_enable_x64``;
            default: float64 if enabled, else float32).
        keep_nees: bool, also return every run's NEES (``(N, K)``, memory ``8 N K`` bytes; one
            process only).
        nees_hist_times: indices into the recorded times (negative from the end) at which
            the per-run NEES is histogrammed.
        nees_bins: increasing histogram edges (default 200 bins on ``[0, 6·15]``; larger
            values land in the last bin).
        update_every: a filter study: every run propagates its own covariance and takes a
            ``measurement`` every this many steps (an integer from 1 to T), updating with
            :func:`jaximu.errorstate.ekf_update`; the errors are recorded after each update
            (``record_every`` is then ignored), the NEES is against each run's own covariance
            and the NIS is reported. ``None``: open-loop propagation.
        measurement: the filter's measurement, a :class:`PositionFix` (its noise is drawn
            with the same ``sigma`` the filter assumes); ``None``: ``PositionFix()`` with
            ``update_every``. Refused without ``update_every`` (it would be ignored).

    Returns:
        :class:`MonteCarloResult`. Under ``jax.distributed`` every process runs its share of
        the chunks and gets the combined result.

    Raises:
        ValueError: naming the argument, for any of them outside the domain above.
    """
    n_runs = val.check_int("n_runs", n_runs, 2)
    if n_runs > 2**32:
        raise ValueError(f"n_runs must be at most 2**32 (run indices are 32-bit counters), got "
                         f"{n_runs}")
    chunk_size = val.check_int("chunk_size", chunk_size, 1)
    n_keep = val.check_int("n_keep", n_keep, 0)
    confidence = val.check_fraction("confidence", confidence)
    progress = val.check_bool("progress", progress)
    shard = val.check_bool("shard", shard)
    keep_nees = val.check_bool("keep_nees", keep_nees)
    if update_every is not None and measurement is None:
        measurement = PositionFix()
    edges = np.linspace(0.0, 90.0, 201) if nees_bins is None else \
        val.as_numbers("nees_bins", nees_bins)
    if edges.ndim != 1 or len(edges) < 2 or not np.all(np.isfinite(edges)) \
            or np.any(np.diff(edges) <= 0):
        raise ValueError("nees_bins must be a 1-D array of at least 2 finite, strictly "
                         f"increasing edges, got {nees_bins!r}")
    st = _prepare(trajectory, times, P0, noise, key, scheme=scheme, gravity=gravity, b_g0=b_g0,
                  b_a0=b_a0, record_every=record_every, dtype=dtype, update_every=update_every,
                  measurement=measurement)
    K = len(st.rec)
    hist_index = np.atleast_1d(np.asarray(nees_hist_times))
    if hist_index.dtype.kind not in "iu" or np.any((hist_index < -K) | (hist_index >= K)):
        raise ValueError(f"nees_hist_times must be indices into the {K} recorded times "
                         f"(-{K} to {K - 1}), got {nees_hist_times!r}")
    hist_index = hist_index % K
    n_proc, proc = jax.process_count(), jax.process_index()
    if keep_nees and n_proc > 1:
        raise ValueError("keep_nees=True needs one process (the per-run NEES stays on the "
                         f"process that drew the run); pass keep_nees=False under "
                         f"jax.distributed ({n_proc} processes)")

    devices = jax.local_devices() if shard else jax.local_devices()[:1]
    # every process must cut the same chunks: under jax.distributed, balance over the global
    # device count (the same in every process), not over this process's cores
    slots = sum(_in_flight(d) for d in devices) if n_proc == 1 else jax.device_count()
    chunk = _chunk_runs(n_runs, chunk_size, slots)
    n_chunks = -(-n_runs // chunk)
    consts = [jax.device_put(st.consts, d) for d in devices]
    mine = list(range(proc, n_chunks, n_proc))
    acc = _Acc(K, hist_index, edges)
    nees_all = np.zeros((n_runs, K)) if keep_nees else None
    bar = _Progress(n_runs if n_proc == 1 else len(mine) * chunk, progress)
    kw = dict(scheme=st.scheme, seg=st.seg, mode="stats", filt=st.filt)

    def inputs(j, i):
        d = j % len(devices)
        run = np.arange(i * chunk, (i + 1) * chunk, dtype=np.uint64)
        wt = (run < n_runs).astype(st.dtype)
        run = jax.device_put((run % 2**32).astype(np.uint32), devices[d])
        return run, jax.device_put(wt, devices[d]), consts[d]

    def launch(j, i):
        return i, jax.block_until_ready(_chunk(*inputs(j, i), **kw))

    # One scan runs on one core (XLA:CPU runs a while loop's body on the calling thread), so
    # a CPU device gets as many chunks in flight as the process has cores, each from its own
    # thread; other devices one each. Chunks are combined in index order whatever finishes
    # first, so the statistics do not depend on the number of workers.
    workers = sum(_in_flight(d) for d in devices) if len(mine) > 1 else 1
    if workers > 1:  # compile once, before the threads ask for it
        for d in {j % len(devices): None for j in range(min(len(mine), len(devices)))}:
            _chunk.lower(*inputs(d, mine[0]), **kw).compile()
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        pending = []
        for j, i in enumerate(mine):
            pending.append(pool.submit(launch, j, i))
            if len(pending) > workers:
                _collect(pending.pop(0).result(), chunk, n_runs, acc, nees_all, bar)
        for p in pending:
            _collect(p.result(), chunk, n_runs, acc, nees_all, bar)
    bar.close()

    if n_proc > 1:  # combine the processes' sums in process order (the same on every one)
        parts = _allgather_f64(acc.pack())
        acc = _Acc(K, hist_index, edges)
        for row in parts:
            acc.add(acc.unpack(row))
    mean = acc.mean
    cov = acc.M2 / (acc.n - 1)
    lo, hi = chi2_interval(15 * n_runs, confidence)
    keep = _sample_errors(st, min(n_keep, n_runs)) if n_keep else np.zeros((0, K, 15))
    predicted, nis_mean, nis_bounds = st.P_rec, None, None
    if st.filt:
        predicted = acc.P_sum / n_runs
        nis_mean = acc.nis_sum / n_runs
        nis_bounds = np.array(chi2_interval(3 * n_runs, confidence)) / n_runs
    # the NEES is undefined where the covariance is singular to the dtype's precision (the
    # filter study's judged on the runs' average): NaN there, never a number from rounding
    undefined = ~_tolerances.definiteness(predicted, st.dtype)[0]
    nees_mean = np.where(undefined, np.nan, acc.nees_sum / n_runs)
    hist = np.where(undefined[hist_index][:, None], np.nan, acc.hist)
    if nees_all is not None:
        nees_all[:, undefined] = np.nan
    settings = dict(trajectory=getattr(trajectory, "name", repr(trajectory)), n_runs=n_runs,
                    scheme=scheme,
                    record_every=int(record_every), n_steps=len(st.consts["dt"]),
                    dtype=jnp.dtype(st.dtype).name, confidence=confidence,
                    key=np.asarray(st.consts["keys"][0]).tolist(),
                    chunk_size=min(chunk_size, n_runs),
                    processes=n_proc, update_every=update_every,
                    measurement_sigma=None if update_every is None or measurement is None else
                    np.asarray(measurement.sigma, float).tolist())
    return MonteCarloResult(
        times=st.times, mean_error=mean, error_cov=cov, predicted_cov=predicted,
        nees=nees_all, nees_mean=nees_mean, nees_bounds=np.array([lo, hi]) / n_runs,
        sample_errors=keep, discretization_error=st.disc, n_runs=n_runs, confidence=confidence,
        nees_hist=hist, nees_hist_edges=edges, nees_hist_index=hist_index,
        nis_mean=nis_mean, nis_bounds=nis_bounds, settings=settings)


def _chunk_runs(n_runs: int, chunk_size: int, slots: int) -> int:
    """Runs per chunk: at most ``chunk_size``, and as even as the ``slots`` that run chunks
    at once (all processes together) allow. Chunks go out in rounds of ``slots``; a last
    round that leaves slots idle takes as long as a full one (10^4 runs in chunks of 2048 on
    two cores are three rounds, the last one half idle; chunks of 1667 fill the three rounds
    and finish 1.2× sooner). At least two lanes: a one-lane program rounds differently
    (``_lane_errors``); a lane past ``n_runs`` has weight 0."""
    rounds = -(-n_runs // (slots * chunk_size))
    return max(2, min(chunk_size, n_runs, -(-n_runs // (rounds * slots))))


def _in_flight(device) -> int:
    """Chunks run at once on ``device``: the cores this process may use on a CPU device
    (``os.sched_getaffinity``: honours ``taskset`` and a scheduler's CPU set), else one."""
    if device.platform != "cpu":
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    # Several CPU devices (--xla_force_host_platform_device_count) share the cores.
    return max(1, cores // max(1, len(jax.local_devices(backend="cpu"))))


def _collect(item, chunk, n_runs, acc, nees_all, bar):
    i, out = item
    n_valid = min(chunk, n_runs - i * chunk)
    lanes = lambda x: np.asarray(x, np.float64)[:, :n_valid]  # noqa: E731  (K, n_valid)
    nees = lanes(out[2])
    if len(out) == 5:
        acc.add_chunk(n_valid, out[0], out[1], nees, out[3], lanes(out[4]))
    else:
        acc.add_chunk(n_valid, out[0], out[1], nees)
    if nees_all is not None:
        nees_all[i * chunk:i * chunk + n_valid] = nees.T
    bar.update(n_valid)


def _lane_errors(study, run):
    """``(K, n, 15)`` errors of the runs ``run`` (``(n,)`` uint32), regenerated.

    A lone run is computed beside a copy of itself: in a program whose lanes are ``(1,)``
    arrays XLA's algebraic simplifier treats the constants as scalars and reorders products
    with them (``(a c)(a c) → (a a)(c c)``), which changes last bits, so the run would not
    equal itself inside a study (chunks have at least two lanes too, :func:`monte_carlo`)."""
    n = run.shape[0]
    if n == 1:
        run = jnp.concatenate([run, run])
    e = _chunk(run, jnp.ones(run.shape[0], study.dtype), study.consts, scheme=study.scheme,
               seg=study.seg, mode="errors", filt=study.filt)
    return e[:, :n]


def _sample_errors(study, n):
    """``(n, K, 15)`` errors of runs ``0..n-1`` (regenerated; see :func:`sample_run`)."""
    e = _lane_errors(study, jnp.arange(n, dtype=jnp.uint32))
    return np.swapaxes(np.asarray(e, np.float64), 0, 1)


class Run(NamedTuple):
    """One run of a study, regenerated by :func:`sample_run` (numpy, float64 copies).

    Attributes:
        errors: ``(K, 15)`` ``x_k ⊟ x̂_k`` at the recorded times (as in the study).
        times: ``(K,)`` the recorded times [s].
        gyro, accel: ``(T+1, 3)`` the measured samples ``w_m``, ``a_m`` of the run.
        start: the estimator's initial state ``x̂_0`` (:class:`NavState`, biases included).
        b_g, b_a: ``(T+1, 3)`` the true biases during each sample.
    """
    errors: np.ndarray
    times: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    start: NavState
    b_g: np.ndarray
    b_a: np.ndarray


def sample_run(trajectory: Trajectory, times, P0, noise: ImuNoise, key, i: int, *,
               scheme: str = "euler", gravity=9.81, b_g0=None, b_a0=None,
               record_every: int = 1, dtype=None, update_every=None,
               measurement: PositionFix | None = None) -> Run:
    """Regenerate run ``i`` of :func:`monte_carlo` (same arguments) alone: its errors, which
    equal the study's (``sample_errors[i]``), and its measured IMU samples, true biases and
    initial estimate, for inspection and plotting. ``i``: an integer in ``[0, 2³²)``."""
    i = val.check_int("i", i, 0)
    if i >= 2**32:
        raise ValueError(f"i must be below 2**32, got {i}")
    st = _prepare(trajectory, times, P0, noise, key, scheme=scheme, gravity=gravity, b_g0=b_g0,
                  b_a0=b_a0, record_every=record_every, dtype=dtype, update_every=update_every,
                  measurement=measurement, nees=False)
    run = jnp.asarray([i], jnp.uint32)
    e = _lane_errors(st, run)[:, 0]
    gyro, accel, b, start = _measured(run, st.consts)
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    return Run(f64(e), st.times, f64(gyro), f64(accel), jax.tree_util.tree_map(f64, start),
               f64(b[:, :3]), f64(b[:, 3:]))
