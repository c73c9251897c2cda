"""The Monte Carlo study's lane kernel (:func:`jaximu.montecarlo.monte_carlo`): every run is a
lane of one structure-of-arrays scan (:mod:`jaximu.kernels.soa`) that draws its noise inside the
step from the counter-based generator (:mod:`jaximu.kernels.rng`), propagates the estimate (and, in
the filter study, its covariance and the position fixes), and reduces the errors at each
recorded time over the lanes (docs/DESIGN.md section 6)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaximu.geometry._vec import V3
from jaximu.geometry.state import NavState, boxminus, boxplus
from jaximu.kernels import rng as _rng
from jaximu.kernels.fast import cov_step_blocks, dense_to_lanes
from jaximu.kernels.lane_forms import mean_step
from jaximu.kernels.lane_math import SOA, _materialise, _rows
from jaximu.schemes._blocks import UPPER, blocks_to_dense, kalman_update, whiten
from jaximu.schemes.integrators import SCHEME_OBJECTS

# Streams of the counter-based generator (each a Threefry key; counter = (run, step)):
# pairs 0-2 white noise of sample j (counter j): (n_gx, n_gy), (n_gz, n_ax), (n_ay, n_az);
# pairs 3-5 bias walk of step k (counter k): the same order for (n_wg, n_wa);
# pairs 6-13 the initial error ε (counter 0; 15 of the 16 normals);
# pairs 14-15 the measurement noise of update u (counter u).
_WHITE, _WALK, _INIT, _MEAS = 0, 3, 6, 14
N_STREAMS = 16
_POSITION_H = (None, "I", None, None, None)  # H = [0, I, 0, 0, 0] by column blocks


# --------------------------------------------------------------------------- the kernel


def _u32(x):
    return jnp.asarray(x, jnp.uint32)


def _initial(run, c, rng_loop=True):
    """``(q̂, p̂, v̂, δb_g, δb_a)`` of the runs ``run`` as SoA components: ``x̂_0 = x_0 ⊞ ε``,
    ``δb = b - b̂ = -ε_b``. ``rng_loop``: :func:`jaximu.kernels.rng.threefry2x32`'s ``loop``."""
    dtype = c["dt"].dtype
    z = _rng.normals(c["keys"][_INIT:], run, _u32(0), 8, dtype, loop=rng_loop)[:15]
    # ε = L0 z as an explicit per-lane sum (a matrix product's summation order depends on
    # the number of lanes; this way a run regenerated alone is bit-identical)
    L0 = c["L0"]
    eps = jnp.stack([sum(L0[i, j] * z[j] for j in range(15)) for i in range(15)], -1)
    B = run.shape[0]
    x0 = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (B,) + x.shape), c["x0"])
    start = boxplus(x0.replace(b_g=jnp.zeros_like(x0.b_g), b_a=jnp.zeros_like(x0.b_a)), eps)
    comps = lambda x: tuple(x[:, i] for i in range(x.shape[1]))  # noqa: E731
    return (
        comps(start.q),
        V3(*comps(start.p)),
        V3(*comps(start.v)),
        -V3(*comps(start.b_g)),
        -V3(*comps(start.b_a)),
    )


def _draw(run, j, k, c, rng_loop):
    """The step's 12 normals, materialised: white noise of sample ``j`` (streams 0-2) and the
    bias walk of step ``k`` (streams 3-5), hashed together. (Materialised: XLA:CPU would
    otherwise recompute the hash in every fusion that reads one of its outputs.)"""
    return _rng.normals_at(
        c["keys"], run, [j] * 3 + [k] * 3, c["dt"].dtype, stage=_materialise, loop=rng_loop
    )


def _sample(n, w, a, sd, dbg, dba):
    """Bias-corrected sample: ``ω = ω_true + δb_g + σ_g/√dt n_g`` and ``f = f_true + δb_a +
    σ_a/√dt n_a`` (``w``, ``a``, ``sd``: the sample's true signals and its 6 white-noise
    standard deviations; ``n``: its 6 white normals)."""
    omega = V3(*(w[i] + dbg[i] + sd[i] * n[i] for i in range(3)))
    f = V3(*(a[i] + dba[i] + sd[3 + i] * n[3 + i] for i in range(3)))
    return omega, f


def _walk(n, sw, dbg, dba):
    """Bias errors after a walk step (``n``: its 6 normals; ``sw``: their 6 std)."""
    return (
        V3(*(dbg[i] + sw[i] * n[i] for i in range(3))),
        V3(*(dba[i] + sw[3 + i] * n[3 + i] for i in range(3))),
    )


def _errors(carry, ref):
    """``(B, 15)`` errors ``x_k ⊟ x̂_k`` of the lanes against the shared reference
    ``ref = (q, p, v)`` (the bias part is ``δb``)."""
    q, p, v, dbg, dba = (carry[k] for k in ("q", "p", "v", "dbg", "dba"))
    st = lambda t: jnp.stack(jnp.broadcast_arrays(*t), -1)  # noqa: E731
    est = NavState(st(q), st(p), st(v), jnp.zeros_like(st(p)), jnp.zeros_like(st(p)))
    B = est.p.shape[0]
    truth = NavState(*(jnp.broadcast_to(x, (B,) + x.shape) for x in ref), st(dbg), st(dba))
    return boxminus(truth, est)


def _run_lanes(run, wt, c, *, scheme, seg, mode, filt, unroll=1, rng_loop=True):
    """Propagate the runs ``run`` (``(B,)`` uint32, the lanes) through all segments.

    ``seg = (length, count, remainder)``: ``count`` segments of ``length`` steps and one of
    ``remainder`` steps (if > 0), each ending at a recorded time. With ``filt`` every run
    also propagates its covariance and, at the end of each full segment, takes a position
    fix (:func:`jaximu.errorstate.ekf_update`); the errors are recorded after the update.
    ``mode``: ``"stats"`` gives per recorded time the tuple of :func:`_lane_stats` over the
    lanes weighted by ``wt``; ``"errors"``: ``(K, B, 15)`` errors. ``unroll`` (steps per
    iteration of the step loop) and ``rng_loop`` (the hash's rounds in a loop) are the
    device's route (:data:`jaximu.engine._dispatch.MONTE_CARLO`): the same numbers either way.
    """
    sch = SCHEME_OBJECTS[scheme]
    nxt = sch.uses_next_sample
    L, n_seg, rem = seg
    dtype = c["dt"].dtype
    B = run.shape[0]
    q, p, v, dbg, dba = _initial(run, c, rng_loop)
    carry = dict(q=q, p=p, v=v, dbg=dbg, dba=dba)
    if nxt:
        w0, a0 = (tuple(x[i] for i in range(3)) for x in (c["w0"], c["a0"]))
        n0 = _rng.normals(c["keys"][_WHITE : _WHITE + 3], run, _u32(0), 3, dtype, loop=rng_loop)
        carry["s"] = _sample(n0, w0, a0, tuple(c["sd0"][i] for i in range(6)), dbg, dba)
    if filt:
        carry["P"] = dense_to_lanes(jnp.broadcast_to(c["P0"], (B, 15, 15)))
    g = V3(*(c["g"][i] for i in range(3)))

    def step(carry, xs):
        k, row = xs
        # a materialised copy: a dynamic slice of the scan inputs inside the lane fusions
        # stops LLVM from vectorising them (as in the SoA covariance kernels); one row, one copy
        row = _materialise(row)
        w, a, sd, sw, qc = (
            tuple(row[i] for i in range(lo, hi))
            for lo, hi in ((0, 3), (3, 6), (6, 12), (12, 18), (19, row.shape[0]))
        )
        h = row[18]
        out = dict(carry)
        dbg, dba = carry["dbg"], carry["dba"]
        if nxt:  # white noise of sample k+1 (the step's end), walk of step k
            n = _draw(run, k + 1, k, c, rng_loop)
            omega0, f0 = carry["s"]
            dbg1, dba1 = _walk(n[6:], sw, dbg, dba)
            omega1, f1 = _sample(n[:6], w, a, sd, dbg1, dba1)
            out["s"] = (omega1, f1)
        else:
            n = _draw(run, k, k, c, rng_loop)
            omega0, f0 = _sample(n[:6], w, a, sd, dbg, dba)
            omega1, f1 = omega0, f0
            dbg1, dba1 = _walk(n[6:], sw, dbg, dba)
        out["dbg"], out["dba"] = dbg1, dba1
        if not filt:
            q1, p1, v1 = mean_step(
                sch, carry["q"], carry["p"], carry["v"], omega0, f0, omega1, f1, h, g
            )
        else:
            q1, p1, v1, out["P"] = cov_step_blocks(
                sch,
                "analytic",
                (carry["q"], tuple(carry["p"]), tuple(carry["v"]), carry["P"]),
                omega0,
                f0,
                omega1,
                f1,
                h,
                g,
                qc,
            )
        out["q"], out["p"], out["v"] = tuple(q1), V3(*p1), V3(*v1)
        return out, None

    T = c["dt"].shape[0]
    qc_all = c["qc"] if filt else jnp.zeros((T, 0), dtype)
    # the per-step inputs as one (T, 19 [+ 12]) table: ω, f, white std, walk std, h [, Q_c]
    table = jnp.concatenate(
        [c["w_in"], c["a_in"], c["sd_in"], c["sw"], c["dt"][:, None], qc_all], 1
    )
    xs_all = (jnp.arange(T, dtype=jnp.uint32), table)

    def update(carry, i):
        """Position fix ``i`` (measurement noise: streams _MEAS, counter i), on the lanes:
        :func:`jaximu.schemes._blocks.kalman_update` (the mathematics of
        :func:`jaximu.errorstate.ekf_update`) on the covariance blocks."""
        ref_p = c["ref"][1][i]
        nu = _rng.normals(
            c["keys"][_MEAS : _MEAS + 2], run, i.astype(jnp.uint32), 2, dtype, loop=rng_loop
        )[:3]
        res = [ref_p[j] - carry["p"][j] + nu[j] * c["meas_sd"][j] for j in range(3)]  # z - p̂
        up = kalman_update(
            dict(zip(UPPER, carry["P"])),
            _POSITION_H,
            SOA.from_arrays(c["meas_R"]),
            _rows([r[None] for r in res], dtype),
            SOA,
        )
        dx = jnp.concatenate([d[:, 0] for d in up.dx], 0).T  # (B, 15)
        st = lambda t: jnp.stack(t, -1)  # noqa: E731
        est = NavState(
            st(carry["q"]), st(carry["p"]), st(carry["v"]), -st(carry["dbg"]), -st(carry["dba"])
        )
        est = boxplus(est, dx)
        comps = lambda x: tuple(x[:, j] for j in range(x.shape[1]))  # noqa: E731
        out = dict(
            carry,
            q=comps(est.q),
            p=V3(*comps(est.p)),
            v=V3(*comps(est.v)),
            dbg=-V3(*comps(est.b_g)),
            dba=-V3(*comps(est.b_a)),
            P=tuple(up.P[k] for k in UPPER),
        )
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
        xs = jax.tree_util.tree_map(lambda x: jax.lax.dynamic_slice_in_dim(x, i * L, L, 0), xs_all)
        carry = jax.lax.scan(step, carry, xs, unroll=min(unroll, L))[0]
        return record(carry, i, True)

    outs = []
    if n_seg:
        carry, out = jax.lax.scan(segment, carry, jnp.arange(n_seg))
        outs.append(out)
    if rem:
        xs = jax.tree_util.tree_map(lambda x: x[n_seg * L :], xs_all)
        carry = jax.lax.scan(step, carry, xs, unroll=min(unroll, rem))[0]
        out = record(carry, jnp.asarray(n_seg), False)[1]
        outs.append(jax.tree_util.tree_map(lambda x: x[None], out))
    return jax.tree_util.tree_map(lambda *x: jnp.concatenate(x, 0), *outs)


def _lane_stats(e, wt, W=None, Pb=None, nis=None):
    """Over the lanes weighted by ``wt``: the mean and centred second moment of the
    ``(B, 15)`` errors, and the per-lane NEES: ``|W e|²`` with ``W`` the inverse Cholesky
    factor of the shared covariance, or ``eᵀ P⁻¹ e`` with each lane's own covariance, its 15
    upper blocks ``Pb`` (``(3, 3, B)``; filter study: then also the weighted sum of ``P``
    and the lanes' NIS). The products are asked for at full precision: on a GPU a float32
    matrix product may otherwise run in TF32 (10-bit mantissa), and the moments and the
    NEES would no longer be the CPU's to rounding."""
    n = jnp.sum(wt)
    mean = jnp.sum(e * wt[:, None], 0) / jnp.maximum(n, 1)
    d = (e - mean) * wt[:, None]
    dot = functools.partial(jnp.matmul, precision=jax.lax.Precision.HIGHEST)
    M2 = dot(d.T, d)
    if Pb is None:
        y = dot(e, W.T)
        return mean, M2, jnp.sum(y * y, -1)
    eT = e.T
    y = whiten(dict(zip(UPPER, Pb)), [eT[3 * i : 3 * i + 3, None] for i in range(5)], SOA)
    nees = sum(jnp.sum(b * b, (0, 1)) for b in y)
    P_sum = blocks_to_dense({k: jnp.sum(b * wt, -1) for k, b in zip(UPPER, Pb)})
    return mean, M2, nees, P_sum, nis


@functools.partial(jax.jit, static_argnames=("scheme", "seg", "mode", "filt", "unroll", "rng_loop"))
def run_chunk(run, wt, c, *, scheme, seg, mode, filt=False, unroll=1, rng_loop=True):
    """The jitted lane kernel (:func:`_run_lanes`). Every caller gives it at least two lanes:
    a one-lane program rounds differently (:func:`jaximu.montecarlo._lane_errors`), so the
    rule is checked here, at trace time, where a new caller would break it."""
    if run.shape[0] < 2:
        raise AssertionError(f"run_chunk needs at least two lanes, got {run.shape[0]}")
    return _run_lanes(
        run, wt, c, scheme=scheme, seg=seg, mode=mode, filt=filt, unroll=unroll, rng_loop=rng_loop
    )


@jax.jit
def measured_run(run, c):
    """Measured samples, true biases and initial estimate of one run (``run``: ``(1,)``), from
    the same streams and counters as the kernel."""
    q, p, v, dbg, dba = _initial(run, c)
    T = c["dt"].shape[0]
    ks = jnp.arange(T + 1, dtype=jnp.uint32)
    dtype = c["dt"].dtype
    n = jnp.stack(_rng.normals(c["keys"][_WHITE : _WHITE + 3], run[0], ks, 3, dtype), -1)
    m = jnp.stack(_rng.normals(c["keys"][_WALK : _WALK + 3], run[0], ks[:T], 3, dtype), -1)
    db = jnp.concatenate([jnp.zeros((1, 6), dtype), jnp.cumsum(m * c["sw"], 0)])  # (T+1, 6)
    b = c["b0"] + db  # true biases during each sample
    noisy = n * c["sd"]
    st = lambda t: jnp.stack(t, -1)[0]  # noqa: E731
    b_hat = c["b0"] - jnp.concatenate([st(dbg), st(dba)])
    start = NavState(st(q), st(p), st(v), b_hat[:3], b_hat[3:])
    return c["gyro"] + b[:, :3] + noisy[:, :3], c["accel"] + b[:, 3:] + noisy[:, 3:], b, start
