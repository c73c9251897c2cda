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
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine import _dispatch
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.noise import ImuNoise
from jaximu.geometry.state import NavState
from jaximu.kernels.montecarlo_lanes import measured_run, run_chunk
from jaximu.studies._montecarlo_result import MonteCarloResult, chi2_interval, load_result
from jaximu.studies._montecarlo_setup import PositionFix, _prepare
from jaximu.studies._montecarlo_stats import _Acc, _allgather_f64, _Progress
from jaximu.studies.simulate import Trajectory

__all__ = [
    "MonteCarloResult",
    "PositionFix",
    "monte_carlo",
    "sample_run",
    "chi2_interval",
    "load_result",
]


# --------------------------------------------------------------------------- the study


def monte_carlo(
    trajectory: Trajectory,
    times,
    P0,
    noise: ImuNoise,
    n_runs: int,
    key,
    *,
    scheme: str = "euler",
    gravity=9.81,
    b_g0=None,
    b_a0=None,
    record_every: int = 1,
    chunk_size: int | None = None,
    n_keep: int = 100,
    confidence: float = 0.95,
    progress: bool = False,
    shard: bool = True,
    dtype=None,
    keep_nees: bool = False,
    nees_hist_times=(-1,),
    nees_bins=None,
    update_every: int | None = None,
    measurement: PositionFix | None = None,
) -> MonteCarloResult:
    """Monte Carlo covariance study of ``n_runs`` noisy copies of one trajectory.

    Args:
        trajectory: the true motion, a :class:`jaximu.simulate.Trajectory`.
        times: ``(T+1,)`` sample times [s], finite and strictly increasing, at least 2; T
            steps (the samples are the interval ends).
        P0: ``(15, 15)`` initial error covariance ``[dθ, dp, dv, db_g, db_a]``, symmetric
            positive semi-definite (judged per axis, as
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
            memory ``O(chunk · K)``, independent of ``n_runs``. Default: the device's
            (:data:`jaximu.engine._dispatch.MONTE_CARLO`: 2048 on a CPU, where each core runs
            a chunk, 2¹⁷ on an accelerator, which one chunk fills). Chunks are made as even as
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
        raise ValueError(
            f"n_runs must be at most 2**32 (run indices are 32-bit counters), got {n_runs}"
        )
    route = _dispatch.monte_carlo_route()
    chunk_size = (
        route.chunk_runs if chunk_size is None else val.check_int("chunk_size", chunk_size, 1)
    )
    n_keep = val.check_int("n_keep", n_keep, 0)
    confidence = val.check_fraction("confidence", confidence)
    progress = val.check_bool("progress", progress)
    shard = val.check_bool("shard", shard)
    keep_nees = val.check_bool("keep_nees", keep_nees)
    if update_every is not None and measurement is None:
        measurement = PositionFix()
    edges = (
        np.linspace(0.0, 90.0, 201) if nees_bins is None else val.as_numbers("nees_bins", nees_bins)
    )
    if (
        edges.ndim != 1
        or len(edges) < 2
        or not np.all(np.isfinite(edges))
        or np.any(np.diff(edges) <= 0)
    ):
        raise ValueError(
            "nees_bins must be a 1-D array of at least 2 finite, strictly "
            f"increasing edges, got {nees_bins!r}"
        )
    st = _prepare(
        trajectory,
        times,
        P0,
        noise,
        key,
        scheme=scheme,
        gravity=gravity,
        b_g0=b_g0,
        b_a0=b_a0,
        record_every=record_every,
        dtype=dtype,
        update_every=update_every,
        measurement=measurement,
    )
    K = len(st.rec)
    hist_index = np.atleast_1d(np.asarray(nees_hist_times))
    if hist_index.dtype.kind not in "iu" or np.any((hist_index < -K) | (hist_index >= K)):
        raise ValueError(
            f"nees_hist_times must be indices into the {K} recorded times "
            f"(-{K} to {K - 1}), got {nees_hist_times!r}"
        )
    hist_index = hist_index % K
    n_proc, proc = jax.process_count(), jax.process_index()
    if keep_nees and n_proc > 1:
        raise ValueError(
            "keep_nees=True needs one process (the per-run NEES stays on the "
            f"process that drew the run); pass keep_nees=False under "
            f"jax.distributed ({n_proc} processes)"
        )

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
    kw = dict(
        _route_options(route, st.filt), scheme=st.scheme, seg=st.seg, mode="stats", filt=st.filt
    )

    def inputs(j, i):
        d = j % len(devices)
        run = np.arange(i * chunk, (i + 1) * chunk, dtype=np.uint64)
        wt = (run < n_runs).astype(st.dtype)
        run = jax.device_put((run % 2**32).astype(np.uint32), devices[d])
        return run, jax.device_put(wt, devices[d]), consts[d]

    def launch(j, i):
        return i, jax.block_until_ready(run_chunk(*inputs(j, i), **kw))

    # One scan runs on one core (XLA:CPU runs a while loop's body on the calling thread), so
    # a CPU device gets as many chunks in flight as the process has cores, each from its own
    # thread; other devices one each. Chunks are combined in index order whatever finishes
    # first, so the statistics do not depend on the number of workers.
    workers = sum(_in_flight(d) for d in devices) if len(mine) > 1 else 1
    if workers > 1:  # compile once, before the threads ask for it
        for d in {j % len(devices): None for j in range(min(len(mine), len(devices)))}:
            run_chunk.lower(*inputs(d, mine[0]), **kw).compile()
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
    settings = dict(
        trajectory=getattr(trajectory, "name", repr(trajectory)),
        n_runs=n_runs,
        scheme=scheme,
        record_every=int(record_every),
        n_steps=len(st.consts["dt"]),
        dtype=jnp.dtype(st.dtype).name,
        confidence=confidence,
        key=np.asarray(st.consts["keys"][0]).tolist(),
        chunk_size=min(chunk_size, n_runs),
        processes=n_proc,
        update_every=update_every,
        measurement_sigma=None
        if update_every is None or measurement is None
        else np.asarray(measurement.sigma, float).tolist(),
    )
    return MonteCarloResult(
        times=st.times,
        mean_error=mean,
        error_cov=cov,
        predicted_cov=predicted,
        nees=nees_all,
        nees_mean=nees_mean,
        nees_bounds=np.array([lo, hi]) / n_runs,
        sample_errors=keep,
        discretization_error=st.disc,
        n_runs=n_runs,
        confidence=confidence,
        nees_hist=hist,
        nees_hist_edges=edges,
        nees_hist_index=hist_index,
        nis_mean=nis_mean,
        nis_bounds=nis_bounds,
        settings=settings,
    )


def _chunk_runs(n_runs: int, chunk_size: int, slots: int) -> int:
    """Runs per chunk: at most ``chunk_size``, and as even as the ``slots`` that run chunks
    at once (all processes together) allow. Chunks go out in rounds of ``slots``; a last
    round that leaves slots idle takes as long as a full one (10^4 runs in chunks of 2048 on
    two cores are three rounds, the last one half idle; chunks of 1667 fill the three rounds
    and finish 1.2× sooner). At least two lanes: a one-lane program rounds differently
    (``_lane_errors``); a lane past ``n_runs`` has weight 0."""
    rounds = -(-n_runs // (slots * chunk_size))
    return max(2, min(chunk_size, n_runs, -(-n_runs // (rounds * slots))))


def _route_options(route, filt) -> dict:
    """The lane kernel's keywords of a :class:`jaximu.engine._dispatch.MonteCarloRoute` for
    an open-loop (``filt=False``) or a filter study."""
    return dict(unroll=route.filter_unroll if filt else route.unroll, rng_loop=route.rng_loop)


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
        nees_all[i * chunk : i * chunk + n_valid] = nees.T
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
    e = run_chunk(
        run,
        jnp.ones(run.shape[0], study.dtype),
        study.consts,
        scheme=study.scheme,
        seg=study.seg,
        mode="errors",
        filt=study.filt,
        **_route_options(_dispatch.monte_carlo_route(), study.filt),
    )
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


def sample_run(
    trajectory: Trajectory,
    times,
    P0,
    noise: ImuNoise,
    key,
    i: int,
    *,
    scheme: str = "euler",
    gravity=9.81,
    b_g0=None,
    b_a0=None,
    record_every: int = 1,
    dtype=None,
    update_every=None,
    measurement: PositionFix | None = None,
) -> Run:
    """Regenerate run ``i`` of :func:`monte_carlo` (same arguments) alone: its errors, which
    equal the study's (``sample_errors[i]``), and its measured IMU samples, true biases and
    initial estimate, for inspection and plotting. ``i``: an integer in ``[0, 2³²)``."""
    i = val.check_int("i", i, 0)
    if i >= 2**32:
        raise ValueError(f"i must be below 2**32, got {i}")
    st = _prepare(
        trajectory,
        times,
        P0,
        noise,
        key,
        scheme=scheme,
        gravity=gravity,
        b_g0=b_g0,
        b_a0=b_a0,
        record_every=record_every,
        dtype=dtype,
        update_every=update_every,
        measurement=measurement,
        nees=False,
    )
    run = jnp.asarray([i], jnp.uint32)
    e = _lane_errors(st, run)[:, 0]
    gyro, accel, b, start = measured_run(run, st.consts)
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    return Run(
        f64(e),
        st.times,
        f64(gyro),
        f64(accel),
        jax.tree_util.tree_map(f64, start),
        f64(b[:, :3]),
        f64(b[:, 3:]),
    )
