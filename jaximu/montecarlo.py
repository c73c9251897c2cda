"""Monte Carlo covariance studies: does the linearised covariance match the real spread?

For one true motion, N noisy IMU streams are drawn (white noise, bias random walk, an
initial-state error from ``P0``), each is propagated, and the errors are compared with the
covariance that :func:`jaximu.propagate_covariance` predicts. This is what GTSAM's
``ScenarioRunner::estimateCovariance`` does in a serial loop; here the runs are the lanes
of one structure-of-arrays scan (:mod:`jaximu._soa`), and the noise is drawn inside the
scan step from a counter-based generator (:mod:`jaximu._rng`):

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
import functools
import json
import math
import os
import pathlib
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import _rng
from jaximu import _validation as val
from jaximu._blocks import UPPER, blocks_to_dense, kalman_update, whiten
from jaximu._soa import SOA, _materialise, _rows, mean_step
from jaximu._vec import V3
from jaximu.errors import Fix, InputError
from jaximu.errorstate import propagate_covariance
from jaximu.integrators import SCHEME_OBJECTS
from jaximu.noise import ImuNoise
from jaximu.propagate import _propagate
from jaximu.simulate import Trajectory, ideal_imu, true_states
from jaximu.state import NavState, boxminus, boxplus

__all__ = ["MonteCarloResult", "PositionFix", "monte_carlo", "sample_run", "chi2_interval",
           "load_result"]

# Streams of the counter-based generator (each a Threefry key; counter = (run, step)):
# pairs 0-2 white noise of sample j (counter j): (n_gx, n_gy), (n_gz, n_ax), (n_ay, n_az);
# pairs 3-5 bias walk of step k (counter k): the same order for (n_wg, n_wa);
# pairs 6-13 the initial error ε (counter 0; 15 of the 16 normals);
# pairs 14-15 the measurement noise of update u (counter u).
_WHITE, _WALK, _INIT, _MEAS = 0, 3, 6, 14
_N_STREAMS = 16
_POSITION_H = (None, "I", None, None, None)  # H = [0, I, 0, 0, 0] by column blocks


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
            (:func:`jaximu._validation.definiteness`; the filter study's judged on the runs'
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
        arrays = {k: np.asarray(v) for k, v in self._asdict().items()
                  if v is not None and k not in ("settings", "n_runs", "confidence")}
        meta = dict(settings=self.settings or {}, n_runs=self.n_runs, confidence=self.confidence,
                    format=_FORMAT)
        np.savez(p, __meta__=np.asarray(json.dumps(meta)), **arrays)


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
    return MonteCarloResult(**{k: fields.get(k) for k in MonteCarloResult._fields
                               if k not in ("settings", "n_runs", "confidence")},
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


# --------------------------------------------------------------------------- progress


class _Progress:
    """tqdm when installed, else a line on stderr every second: runs done, runs/s, ETA."""

    def __init__(self, total, enabled):
        self.total, self.done, self.bar = total, 0, None
        self.enabled = enabled
        self.t0 = self.last = time.perf_counter()
        if enabled:
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(total=total, unit="run", desc="Monte Carlo")
            except ImportError:
                pass

    def update(self, n):
        self.done += n
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n)
            return
        now = time.perf_counter()
        if now - self.last >= 1.0 or self.done == self.total:
            self.last = now
            rate = self.done / max(now - self.t0, 1e-9)
            eta = (self.total - self.done) / max(rate, 1e-9)
            print(f"\rMonte Carlo: {self.done}/{self.total} runs, {rate:,.0f} runs/s, "
                  f"ETA {eta:.0f} s", end="", file=sys.stderr, flush=True)

    def close(self):
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            print(file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- the kernel


def _u32(x):
    return jnp.asarray(x, jnp.uint32)


def _initial(run, c):
    """``(q̂, p̂, v̂, δb_g, δb_a)`` of the runs ``run`` as SoA components: ``x̂_0 = x_0 ⊞ ε``,
    ``δb = b - b̂ = -ε_b``."""
    dtype = c["dt"].dtype
    z = _rng.normals(c["keys"][_INIT:], run, _u32(0), 8, dtype)[:15]
    # ε = L0 z as an explicit per-lane sum (a matrix product's summation order depends on
    # the number of lanes; this way a run regenerated alone is bit-identical)
    L0 = c["L0"]
    eps = jnp.stack([sum(L0[i, j] * z[j] for j in range(15)) for i in range(15)], -1)
    B = run.shape[0]
    x0 = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (B,) + x.shape), c["x0"])
    start = boxplus(x0.replace(b_g=jnp.zeros_like(x0.b_g), b_a=jnp.zeros_like(x0.b_a)), eps)
    comps = lambda x: tuple(x[:, i] for i in range(x.shape[1]))  # noqa: E731
    return (comps(start.q), V3(*comps(start.p)), V3(*comps(start.v)), -V3(*comps(start.b_g)),
            -V3(*comps(start.b_a)))


def _draw(run, j, k, c):
    """The step's 12 normals, materialised: white noise of sample ``j`` (streams 0-2) and the
    bias walk of step ``k`` (streams 3-5), hashed together. (Materialised: XLA:CPU would
    otherwise recompute the hash in every fusion that reads one of its outputs.)"""
    return _rng.normals_at(c["keys"], run, [j] * 3 + [k] * 3, c["dt"].dtype,
                           stage=_materialise)


def _sample(n, w, a, sd, dbg, dba):
    """Bias-corrected sample: ``ω = ω_true + δb_g + σ_g/√dt n_g`` and ``f = f_true + δb_a +
    σ_a/√dt n_a`` (``w``, ``a``, ``sd``: the sample's true signals and its 6 white-noise
    standard deviations; ``n``: its 6 white normals)."""
    omega = V3(*(w[i] + dbg[i] + sd[i] * n[i] for i in range(3)))
    f = V3(*(a[i] + dba[i] + sd[3 + i] * n[3 + i] for i in range(3)))
    return omega, f


def _walk(n, sw, dbg, dba):
    """Bias errors after a walk step (``n``: its 6 normals; ``sw``: their 6 std)."""
    return (V3(*(dbg[i] + sw[i] * n[i] for i in range(3))),
            V3(*(dba[i] + sw[3 + i] * n[3 + i] for i in range(3))))


def _errors(carry, ref):
    """``(B, 15)`` errors ``x_k ⊟ x̂_k`` of the lanes against the shared reference
    ``ref = (q, p, v)`` (the bias part is ``δb``)."""
    q, p, v, dbg, dba = (carry[k] for k in ("q", "p", "v", "dbg", "dba"))
    st = lambda t: jnp.stack(jnp.broadcast_arrays(*t), -1)  # noqa: E731
    est = NavState(st(q), st(p), st(v), jnp.zeros_like(st(p)), jnp.zeros_like(st(p)))
    B = est.p.shape[0]
    truth = NavState(*(jnp.broadcast_to(x, (B,) + x.shape) for x in ref), st(dbg), st(dba))
    return boxminus(truth, est)


def _run_lanes(run, wt, c, *, scheme, seg, mode, filt):
    """Propagate the runs ``run`` (``(B,)`` uint32, the lanes) through all segments.

    ``seg = (length, count, remainder)``: ``count`` segments of ``length`` steps and one of
    ``remainder`` steps (if > 0), each ending at a recorded time. With ``filt`` every run
    also propagates its covariance and, at the end of each full segment, takes a position
    fix (:func:`jaximu.errorstate.ekf_update`); the errors are recorded after the update.
    ``mode``: ``"stats"`` gives per recorded time the tuple of :func:`_lane_stats` over the
    lanes weighted by ``wt``; ``"errors"``: ``(K, B, 15)`` errors.
    """
    from jaximu._fast import cov_step_blocks, dense_to_blocks

    sch = SCHEME_OBJECTS[scheme]
    nxt = sch.uses_next_sample
    L, n_seg, rem = seg
    dtype = c["dt"].dtype
    B = run.shape[0]
    q, p, v, dbg, dba = _initial(run, c)
    carry = dict(q=q, p=p, v=v, dbg=dbg, dba=dba)
    if nxt:
        w0, a0 = (tuple(x[i] for i in range(3)) for x in (c["w0"], c["a0"]))
        n0 = _rng.normals(c["keys"][_WHITE:_WHITE + 3], run, _u32(0), 3, dtype)
        carry["s"] = _sample(n0, w0, a0, tuple(c["sd0"][i] for i in range(6)), dbg, dba)
    if filt:
        carry["P"] = dense_to_blocks(jnp.broadcast_to(c["P0"], (B, 15, 15)))
    g = V3(*(c["g"][i] for i in range(3)))

    def step(carry, xs):
        k, row = xs
        # a materialised copy: a dynamic slice of the scan inputs inside the lane fusions
        # stops LLVM from vectorising them (as in the SoA covariance kernels); one row, one copy
        row = _materialise(row)
        w, a, sd, sw, qc = (tuple(row[i] for i in range(lo, hi)) for lo, hi in (
            (0, 3), (3, 6), (6, 12), (12, 18), (19, row.shape[0])))
        h = row[18]
        out = dict(carry)
        dbg, dba = carry["dbg"], carry["dba"]
        if nxt:  # white noise of sample k+1 (the step's end), walk of step k
            n = _draw(run, k + 1, k, c)
            omega0, f0 = carry["s"]
            dbg1, dba1 = _walk(n[6:], sw, dbg, dba)
            omega1, f1 = _sample(n[:6], w, a, sd, dbg1, dba1)
            out["s"] = (omega1, f1)
        else:
            n = _draw(run, k, k, c)
            omega0, f0 = _sample(n[:6], w, a, sd, dbg, dba)
            omega1, f1 = omega0, f0
            dbg1, dba1 = _walk(n[6:], sw, dbg, dba)
        out["dbg"], out["dba"] = dbg1, dba1
        if not filt:
            q1, p1, v1 = mean_step(sch, carry["q"], carry["p"], carry["v"], omega0, f0, omega1,
                                   f1, h, g)
        else:
            q1, p1, v1, out["P"] = cov_step_blocks(
                sch, "analytic", (carry["q"], tuple(carry["p"]), tuple(carry["v"]), carry["P"]),
                omega0, f0, omega1, f1, h, g, qc)
        out["q"], out["p"], out["v"] = tuple(q1), V3(*p1), V3(*v1)
        return out, None

    T = c["dt"].shape[0]
    qc_all = c["qc"] if filt else jnp.zeros((T, 0), dtype)
    # the per-step inputs as one (T, 19 [+ 12]) table: ω, f, white std, walk std, h [, Q_c]
    table = jnp.concatenate([c["w_in"], c["a_in"], c["sd_in"], c["sw"], c["dt"][:, None],
                             qc_all], 1)
    xs_all = (jnp.arange(T, dtype=jnp.uint32), table)

    def update(carry, i):
        """Position fix ``i`` (measurement noise: streams _MEAS, counter i), on the lanes:
        :func:`jaximu._blocks.kalman_update` (the mathematics of
        :func:`jaximu.errorstate.ekf_update`) on the covariance blocks."""
        ref_p = c["ref"][1][i]
        nu = _rng.normals(c["keys"][_MEAS:_MEAS + 2], run, i.astype(jnp.uint32), 2, dtype)[:3]
        res = [ref_p[j] - carry["p"][j] + nu[j] * c["meas_sd"][j] for j in range(3)]  # z - p̂
        up = kalman_update(dict(zip(UPPER, carry["P"])), _POSITION_H,
                           SOA.from_arrays(c["meas_R"]), _rows([r[None] for r in res], dtype),
                           SOA)
        dx = jnp.concatenate([d[:, 0] for d in up.dx], 0).T  # (B, 15)
        st = lambda t: jnp.stack(t, -1)  # noqa: E731
        est = NavState(st(carry["q"]), st(carry["p"]), st(carry["v"]), -st(carry["dbg"]),
                       -st(carry["dba"]))
        est = boxplus(est, dx)
        comps = lambda x: tuple(x[:, j] for j in range(x.shape[1]))  # noqa: E731
        out = dict(carry, q=comps(est.q), p=V3(*comps(est.p)), v=V3(*comps(est.v)),
                   dbg=-V3(*comps(est.b_g)), dba=-V3(*comps(est.b_a)),
                   P=tuple(up.P[k] for k in UPPER))
        if nxt:  # the carried sample is corrected with the new bias estimate
            omega, f = carry["s"]
            out["s"] = (omega + (out["dbg"] - carry["dbg"]), f + (out["dba"] - carry["dba"]))
        return out, up.nis[0, 0]

    def record(carry, i, with_update):
        nis = None
        if filt and with_update:
            carry, nis = update(carry, i)
        ref = tuple(x[i] for x in c["ref"])
        e = _errors(carry, ref)
        if mode == "errors":
            return carry, e
        if not filt:
            return carry, _lane_stats(e, wt, W=c["W"][i])
        if nis is None:
            nis = jnp.full((B,), jnp.nan, dtype)
        return carry, _lane_stats(e, wt, Pb=carry["P"], nis=nis)

    def segment(carry, i):
        xs = jax.tree_util.tree_map(
            lambda x: jax.lax.dynamic_slice_in_dim(x, i * L, L, 0), xs_all)
        carry = jax.lax.scan(step, carry, xs)[0]
        return record(carry, i, True)

    outs = []
    if n_seg:
        carry, out = jax.lax.scan(segment, carry, jnp.arange(n_seg))
        outs.append(out)
    if rem:
        xs = jax.tree_util.tree_map(lambda x: x[n_seg * L:], xs_all)
        carry = jax.lax.scan(step, carry, xs)[0]
        out = record(carry, jnp.asarray(n_seg), False)[1]
        outs.append(jax.tree_util.tree_map(lambda x: x[None], out))
    return jax.tree_util.tree_map(lambda *x: jnp.concatenate(x, 0), *outs)


def _lane_stats(e, wt, W=None, Pb=None, nis=None):
    """Over the lanes weighted by ``wt``: the mean and centred second moment of the
    ``(B, 15)`` errors, and the per-lane NEES: ``|W e|²`` with ``W`` the inverse Cholesky
    factor of the shared covariance, or ``eᵀ P⁻¹ e`` with each lane's own covariance, its 15
    upper blocks ``Pb`` (``(3, 3, B)``; filter study: then also the weighted sum of ``P``
    and the lanes' NIS)."""
    n = jnp.sum(wt)
    mean = jnp.sum(e * wt[:, None], 0) / jnp.maximum(n, 1)
    d = (e - mean) * wt[:, None]
    if Pb is None:
        y = e @ W.T
        return mean, d.T @ d, jnp.sum(y * y, -1)
    eT = e.T
    y = whiten(dict(zip(UPPER, Pb)), [eT[3 * i:3 * i + 3, None] for i in range(5)], SOA)
    nees = sum(jnp.sum(b * b, (0, 1)) for b in y)
    P_sum = blocks_to_dense({k: jnp.sum(b * wt, -1) for k, b in zip(UPPER, Pb)})
    return mean, d.T @ d, nees, P_sum, nis


@functools.partial(jax.jit, static_argnames=("scheme", "seg", "mode", "filt"))
def _chunk(run, wt, c, *, scheme, seg, mode, filt=False):
    """The jitted lane kernel (:func:`_run_lanes`). Every caller gives it at least two lanes:
    a one-lane program rounds differently (:func:`_lane_errors`), so the rule is checked
    here, at trace time, where a new caller would break it."""
    if run.shape[0] < 2:
        raise AssertionError(f"_chunk needs at least two lanes, got {run.shape[0]}")
    return _run_lanes(run, wt, c, scheme=scheme, seg=seg, mode=mode, filt=filt)


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
             dtype, update_every=None, measurement=None):
    """Validate the inputs and build the kernel's constants (shared by :func:`monte_carlo`
    and :func:`sample_run`)."""
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
    model_noise = val.check_noise(model_noise, dtype)
    draw_noise = val.check_noise(draw_noise, dtype)
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
        defined = val.definiteness(P_rec, dtype)[0]
        if not defined.any():
            k = len(rec) - 1
            val.check_definite(
                f"the predicted covariance at times[{rec[k] + 1}] = {times[rec[k] + 1]:g} "
                "(and at every recorded time)", P_rec[k], dtype, axes=val.ERROR_AXES,
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


# --------------------------------------------------------------------------- accumulation


class _Acc:
    """Streaming sums over runs, float64 on the host: count, mean and centred second moment
    of the errors per recorded time (Chan, Golub, LeVeque's pairwise update), the sum of the
    NEES, and NEES histograms."""

    def __init__(self, K, hist_index, edges):
        self.n = 0
        self.mean = np.zeros((K, 15))
        self.M2 = np.zeros((K, 15, 15))
        self.nees_sum = np.zeros(K)
        self.hist_index = hist_index
        self.edges = edges
        self.hist = np.zeros((len(hist_index), len(edges) - 1))
        self.nis_sum = np.zeros(K)  # filter study
        self.P_sum = np.zeros((K, 15, 15))

    def add_moments(self, n_b, mean_b, M2_b):
        n_a = self.n
        n = n_a + n_b
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (n_b / n)
        self.M2 = self.M2 + M2_b + np.einsum("ki,kj->kij", delta, delta) * (n_a * n_b / n)
        self.n = n

    def add_chunk(self, n_b, mean_b, M2_b, nees, P_sum=None, nis=None):
        """``nees``: ``(K, n_b)`` per-run NEES of the chunk's valid runs (filter study: also
        the sum of the runs' covariances and ``(K, n_b)`` NIS)."""
        self.add_moments(n_b, np.asarray(mean_b, np.float64), np.asarray(M2_b, np.float64))
        if P_sum is not None:
            self.P_sum += np.asarray(P_sum, np.float64)
            self.nis_sum += nis.sum(1)
        self.nees_sum += nees.sum(1)
        last = len(self.edges) - 2
        for h, k in enumerate(self.hist_index):
            b = np.clip(np.searchsorted(self.edges, nees[k], side="right") - 1, 0, last)
            self.hist[h] += np.bincount(b, minlength=last + 1)

    def add(self, other):
        if other.n:
            self.add_moments(other.n, other.mean, other.M2)
        self.nees_sum += other.nees_sum
        self.hist += other.hist
        self.nis_sum += other.nis_sum
        self.P_sum += other.P_sum

    _PARTS = ("mean", "M2", "nees_sum", "hist", "nis_sum", "P_sum")

    def pack(self):
        return np.concatenate([[self.n]] + [getattr(self, k).ravel() for k in self._PARTS])

    def unpack(self, flat):
        K = len(self.nees_sum)
        other = _Acc(K, self.hist_index, self.edges)
        i = 1
        other.n = int(flat[0])
        for name in self._PARTS:
            shape = getattr(self, name).shape
            size = int(np.prod(shape))
            setattr(other, name, flat[i:i + size].reshape(shape))
            i += size
        return other


def _allgather_f64(x):
    """Every process's float64 vector ``x`` (same length), exactly: sent as uint32 words (the
    transport does not need ``jax_enable_x64``). Returns ``(processes, len)``."""
    from jax.experimental import multihost_utils

    words = np.ascontiguousarray(x, np.float64).view(np.uint32)
    out = np.asarray(multihost_utils.process_allgather(words))
    return out.reshape(jax.process_count(), -1).view(np.float64)


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
    undefined = ~val.definiteness(predicted, st.dtype)[0]
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
                    measurement_sigma=None if update_every is None else
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
                  measurement=measurement)
    run = jnp.asarray([i], jnp.uint32)
    e = _lane_errors(st, run)[:, 0]
    gyro, accel, b, start = _measured(run, st.consts)
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    return Run(f64(e), st.times, f64(gyro), f64(accel), jax.tree_util.tree_map(f64, start),
               f64(b[:, :3]), f64(b[:, 3:]))


@jax.jit
def _measured(run, c):
    """Measured samples, true biases and initial estimate of one run (``run``: ``(1,)``), from
    the same streams and counters as the kernel."""
    q, p, v, dbg, dba = _initial(run, c)
    T = c["dt"].shape[0]
    ks = jnp.arange(T + 1, dtype=jnp.uint32)
    dtype = c["dt"].dtype
    n = jnp.stack(_rng.normals(c["keys"][_WHITE:_WHITE + 3], run[0], ks, 3, dtype), -1)
    m = jnp.stack(_rng.normals(c["keys"][_WALK:_WALK + 3], run[0], ks[:T], 3, dtype), -1)
    db = jnp.concatenate([jnp.zeros((1, 6), dtype), jnp.cumsum(m * c["sw"], 0)])  # (T+1, 6)
    b = c["b0"] + db  # true biases during each sample
    noisy = n * c["sd"]
    st = lambda t: jnp.stack(t, -1)[0]  # noqa: E731
    b_hat = c["b0"] - jnp.concatenate([st(dbg), st(dba)])
    start = NavState(st(q), st(p), st(v), b_hat[:3], b_hat[3:])
    return c["gyro"] + b[:, :3] + noisy[:, :3], c["accel"] + b[:, 3:] + noisy[:, 3:], b, start
