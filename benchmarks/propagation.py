"""Throughput benchmark for jaximu's batched IMU propagation.

Measures samples per second (B·T divided by the run time) of the public functions wrapped
in ``jax.jit``:

* mean-only propagation: ``jaximu.propagate_final`` (final state) and ``jaximu.propagate``
  (every state stored);
* propagation with the 15×15 error-state covariance: ``jaximu.propagate_covariance_final``
  with analytic and autodiff Jacobians, and ``jaximu.propagate_covariance`` (every
  covariance stored) at a size where the output fits in memory;
* a naive reference: ``jax.vmap`` over a per-trajectory ``lax.scan`` Euler step written
  inline below (plain quaternion math), the way one would write it in brax style.

Compile time is measured apart from run time: each case is lowered and compiled ahead of
time (``jax.jit(f).lower(*args).compile()``); the compiled executable then runs at least
three times and the best run is reported. ``first call s`` is compile + the first run, what
a user waits for on the first call of a fresh ``jax.jit``.

Usage (see benchmarks/README.md)::

    python benchmarks/propagation.py              # default grid, ~3 min on an idle 2-core CPU
    python benchmarks/propagation.py --quick      # small sizes, a smoke test (< 1 min)
    python benchmarks/propagation.py --only mean  # or --only cov
    python benchmarks/propagation.py --rss        # each case in its own process, max RSS
    python benchmarks/propagation.py --vector-width 512  # XLA's 512-bit vectors (AVX-512)
    python benchmarks/propagation.py --check benchmarks/results/propagation-baseline-intel-xeon-2cpu.json

``--check BASELINE``: compares every case that BASELINE (an earlier run's JSON, same machine)
also measured, matched by name, dtype and size: a run rate more than 30% below the baseline's
is a regression, and the script exits 1. Compile times over 1.5× the baseline's are listed
too (the limit), and fail the check only with ``--check-compile`` (compile times move
±30% between runs of one commit on this host). Cases the baseline lacks are listed as new.
The committed baseline is commit 342b89a measured by its own script on
the Intel host: rows added since (``vmap``, rotating world, lever arm, autodiff for midpoint
and RK4) have no baseline.

Prints a Markdown table and writes ``benchmarks/results/propagation-<machine>.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax

# The library never enables float64 itself; the caller does, before any array is made.
jax.config.update("jax_enable_x64", True)


def _int_arg(argv, name, default) -> int:
    """``--name N`` read before JAX starts (device count and XLA flags are fixed then)."""
    for i, a in enumerate(argv):
        if a == name and i + 1 < len(argv):
            return int(argv[i + 1])
        if a.startswith(name + "="):
            return int(a.split("=", 1)[1])
    return default


DEVICES = _int_arg(sys.argv[1:], "--devices", 1)
if DEVICES > 1:  # one CPU device per core; every case runs under a mesh of them
    jax.config.update("jax_num_cpu_devices", DEVICES)

VECTOR_WIDTH = _int_arg(sys.argv[1:], "--vector-width", 0)
"""``--vector-width N``: XLA:CPU compiles with N-bit vectors preferred (its flag
``--xla_cpu_prefer_vector_width``, default 256), as a user sets it in ``XLA_FLAGS``; 0 leaves
XLA's default (docs/guide/performance.md, "CPU vector width")."""
VW_FLAG = f"--xla_cpu_prefer_vector_width={VECTOR_WIDTH}"
if VECTOR_WIDTH and VW_FLAG not in os.environ.get("XLA_FLAGS", ""):  # read when JAX starts
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + VW_FLAG).strip()

NO_UNROLL = "--no-loop-unrolling" in sys.argv[1:]
"""``--no-loop-unrolling``: XLA:CPU asks LLVM for no loop unrolling (the backend option
``xla_cpu_disable_loop_unrolling``), as a user sets it in ``XLA_FLAGS``
(docs/guide/performance.md, "Compile time"). The option joins the last
``--xla_backend_extra_options`` list there, if any."""
NO_UNROLL_OPTION = "xla_cpu_disable_loop_unrolling"
if NO_UNROLL and NO_UNROLL_OPTION not in os.environ.get("XLA_FLAGS", ""):
    _flags = os.environ.get("XLA_FLAGS", "").split()
    _extra = [i for i, f in enumerate(_flags) if f.startswith("--xla_backend_extra_options=")]
    if _extra:
        _flags[_extra[-1]] += "," + NO_UNROLL_OPTION
    else:
        _flags.append("--xla_backend_extra_options=" + NO_UNROLL_OPTION)
    os.environ["XLA_FLAGS"] = " ".join(_flags)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS_DIR = HERE / "results"

# Targets for a 2-core CPU, float32, batched (B > 1).
TARGET_MEAN = 100e6  # Euler mean, float32, 1024×1000
TARGET_COV = 10e6  # the same with the 15×15 covariance
# Flag a case when other processes used more than this share of the CPUs while it ran.
BUSY_WARN = 0.10
# --check: a run rate more than 30% below the baseline's (run-to-run noise on a shared 2-core
# VM is ±15-20%), or a compile time over 1.5× the baseline's (the limit), regresses.
RATE_TOLERANCE = 0.30
COMPILE_LIMIT = 1.5

DT = 0.005  # 200 Hz
GYRO_STD = 0.5  # rad/s
ACCEL_STD = 0.5  # m/s² around [0, 0, 9.81] (level, roughly still)
NOISE = jaximu.ImuNoise.euroc()
# Initial covariance of [dθ, dp, dv, db_g, db_a]: 0.1°, 1 cm, 1 cm/s, the biases' spread.
P0_DIAG = np.r_[[np.deg2rad(0.1) ** 2] * 3, [1e-4] * 3, [1e-4] * 3, [1e-4**2] * 3, [1e-3**2] * 3]

EARTH_48 = np.asarray(jaximu.earth_rate(48.0))  # rad/s, east-north-up
# an IMU rotated 40° and 0.39 m from the body's origin (its covariance couples the gyro into
# the specific force through ω×(ω×r): jaximu/geometry/sensor.py)
LEVER_POSE = jaximu.SensorPose.from_rotation(
    np.asarray(jaximu.so3.exp_matrix(jnp.asarray([0.3, -0.5, 0.4]))), np.array([0.3, -0.2, 0.15])
)

# Display order of the cases in the table.
CASE_ORDER = [
    "mean euler final",
    "mean euler final vmap",
    "mean euler all",
    "mean euler all vmap",
    "mean midpoint final",
    "mean midpoint final vmap",
    "mean rk4 final",
    "mean euler final rotating",
    "mean euler final lever",
    "mean euler final matrix",
    "mean euler final quaternion_first_order",
    "mean euler final euler_angles",
    "baseline vmap(scan) euler final",
    "cov analytic euler final",
    "cov analytic euler final vmap",
    "cov analytic euler final rotating",
    "cov analytic euler final lever",
    "cov analytic euler final matrix",
    "cov autodiff euler final",
    "cov autodiff euler final quaternion_first_order",
    "cov autodiff euler final euler_angles",
    "cov analytic midpoint final",
    "cov autodiff midpoint final",
    "cov analytic rk4 final",
    "cov autodiff rk4 final",
    "cov analytic euler all",
    "cov autodiff euler all",
]


# --------------------------------------------------------------------------- the grid


def plan(quick: bool, only: str | None) -> tuple[list[dict], list[str]]:
    """The cases to run, in execution order (size-major, so inputs are made once per size)."""
    dtypes = ["float32", "float64"]
    if quick:
        # Every code path once, few compilations: the sizes say nothing about speed.
        mean_sizes, cov_sizes = [(1, 1000), (64, 100)], [(64, 100)]
        extra_size, extra_dtypes = (64, 100), ["float32"]  # midpoint, rk4, the baseline
        cov_all_size, cov_all_dtypes = (16, 50), ["float32"]
        one_size = (1, 1000)
    else:
        mean_sizes = cov_sizes = [(1, 100_000), (1024, 1000), (16384, 200)]
        extra_size, extra_dtypes = (1024, 1000), dtypes
        cov_all_size, cov_all_dtypes = (1024, 200), dtypes
        one_size = (1, 100_000)
    notes = []
    big_b, big_t = cov_sizes[-1]
    gb = [big_b * big_t * 15 * 15 * np.dtype(d).itemsize / 1e9 for d in dtypes]
    if not quick:
        notes.append(
            f"Covariance cases at the main sizes are final-only: storing every covariance at "
            f"{big_b}×{big_t} would take {gb[0]:.2f} GB (float32) / {gb[1]:.2f} GB (float64) "
            f"for the output alone; 'all' (every covariance stored) is measured at "
            f"{cov_all_size[0]}×{cov_all_size[1]} instead."
        )

    def case(
        section,
        kind,
        scheme,
        save,
        B,
        T,
        dtype,
        jac=None,
        vmap=False,
        rotating=False,
        lever=False,
        attitude="quaternion",
    ):
        world = (
            (" rotating" if rotating else "")
            + (" lever" if lever else "")
            + ("" if attitude == "quaternion" else f" {attitude}")
        )
        if kind == "mean":
            name = f"mean {scheme} {save}" + world
        elif kind == "cov":
            name = f"cov {jac} {scheme} {save}" + world
        else:
            name = f"baseline vmap(scan) {scheme} {save}"
        name += " vmap" if vmap else ""
        return dict(
            section=section,
            name=name,
            kind=kind,
            scheme=scheme,
            jac=jac,
            save=save,
            B=B,
            T=T,
            dtype=dtype,
            vmap=vmap,
            rotating=rotating,
            lever=lever,
            attitude=attitude,
        )

    all_sizes = list(dict.fromkeys(mean_sizes + cov_sizes + [extra_size, cov_all_size, one_size]))
    cases = []
    for B, T in all_sizes:
        for dtype in dtypes:
            extra = (B, T) == extra_size and dtype in extra_dtypes
            if only in (None, "mean"):
                if (B, T) in mean_sizes:
                    cases += [
                        case("mean", "mean", "euler", s, B, T, dtype) for s in ("final", "all")
                    ]
                if extra:
                    cases += [
                        case("mean", "mean", s, "final", B, T, dtype) for s in ("midpoint", "rk4")
                    ]
                    # jax.vmap over trajectories: the same work as the leading-axes rows
                    cases += [
                        case("mean", "mean", "euler", s, B, T, dtype, vmap=True)
                        for s in ("final", "all")
                    ]
                    cases.append(case("mean", "mean", "midpoint", "final", B, T, dtype, vmap=True))
                    # a rotating world (Earth's rate at 48°, the exact transition)
                    cases.append(case("mean", "mean", "euler", "final", B, T, dtype, rotating=True))
                    # a sensor at a lever arm (body_P_sensor: its samples moved to the body)
                    cases.append(case("mean", "mean", "euler", "final", B, T, dtype, lever=True))
                    # the other attitude forms on the same kernels
                    # (docs/guide/propagation.md, "Schemes and attitude forms")
                    cases += [
                        case("mean", "mean", "euler", "final", B, T, dtype, attitude=a)
                        for a in ("matrix", "quaternion_first_order", "euler_angles")
                    ]
                    if dtype == "float32":
                        cases.append(case("mean", "baseline", "euler", "final", B, T, dtype))
            if only in (None, "cov"):
                if (B, T) in cov_sizes:
                    cases += [
                        case("cov", "cov", "euler", "final", B, T, dtype, jac=j)
                        for j in ("analytic", "autodiff")
                    ]
                if extra:
                    cases += [
                        case("cov", "cov", s, "final", B, T, dtype, jac=j)
                        for s in ("midpoint", "rk4")
                        for j in ("analytic", "autodiff")
                    ]
                    cases.append(
                        case("cov", "cov", "euler", "final", B, T, dtype, jac="analytic", vmap=True)
                    )
                    cases.append(
                        case(
                            "cov",
                            "cov",
                            "euler",
                            "final",
                            B,
                            T,
                            dtype,
                            jac="analytic",
                            rotating=True,
                        )
                    )
                    # a sensor at a lever arm (body_P_sensor)
                    cases.append(
                        case(
                            "cov", "cov", "euler", "final", B, T, dtype, jac="analytic", lever=True
                        )
                    )
                    cases.append(
                        case(
                            "cov",
                            "cov",
                            "euler",
                            "final",
                            B,
                            T,
                            dtype,
                            jac="analytic",
                            attitude="matrix",
                        )
                    )
                    cases += [
                        case(
                            "cov", "cov", "euler", "final", B, T, dtype, jac="autodiff", attitude=a
                        )
                        for a in ("quaternion_first_order", "euler_angles")
                    ]
                if (B, T) == cov_all_size and dtype in cov_all_dtypes:
                    cases += [
                        case("cov", "cov", "euler", "all", B, T, dtype, jac=j)
                        for j in ("analytic", "autodiff")
                    ]
                if (B, T) == one_size and dtype in cov_all_dtypes:
                    # one long recording, every covariance stored (in time chunks)
                    cases.append(case("cov", "cov", "euler", "all", B, T, dtype, jac="analytic"))
    return cases, (notes if only in (None, "cov") else [])


# --------------------------------------------------------------------------- inputs


_INPUT_CACHE: dict = {}


def make_inputs(B: int, T: int, dtype: str, seed: int = 0):
    """Random but realistic IMU data, built directly in ``dtype`` (one size cached at a time)."""
    key = (B, T, dtype)
    if key not in _INPUT_CACHE:
        _INPUT_CACHE.clear()
        rng = np.random.default_rng(seed)
        npd = np.dtype(dtype)
        gyro = rng.standard_normal((B, T, 3), dtype=npd)
        gyro *= npd.type(GYRO_STD)
        accel = rng.standard_normal((B, T, 3), dtype=npd)
        accel *= npd.type(ACCEL_STD)
        accel += np.array([0.0, 0.0, 9.81], npd)
        inputs = dict(
            state=jaximu.NavState.identity((B,), jnp.dtype(dtype)),
            gyro=jnp.asarray(gyro),
            accel=jnp.asarray(accel),
            dt=jnp.full((T,), DT, jnp.dtype(dtype)),
            P0=jnp.asarray(np.diag(P0_DIAG), jnp.dtype(dtype)),
        )
        del gyro, accel
        _INPUT_CACHE[key] = inputs
    return _INPUT_CACHE[key]


# --------------------------------------------------------------------------- the baseline


def _quat_mul(a, b):
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def _quat_exp(phi):
    """Exact exponential of a rotation vector, as a quaternion [w, x, y, z]."""
    th2 = jnp.sum(phi * phi)
    th = jnp.sqrt(th2)
    small = th < 1e-4
    safe = jnp.where(small, 1.0, th)
    s = jnp.where(small, 0.5 - th2 / 48.0, jnp.sin(0.5 * safe) / safe)
    return jnp.concatenate([jnp.cos(0.5 * th)[None], s * phi])


def _quat_rotate(q, v):
    u, w = q[1:], q[0]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def baseline_final(q0, p0, v0, gyro, accel, dt):
    """Naive reference: ``vmap`` over one trajectory's ``lax.scan`` of Euler steps.

    Same model as jaximu's Euler scheme (zero-order hold on sample k, exact quaternion
    exponential, ``g_W = [0, 0, -9.81]``), written the obvious way: per-trajectory scan,
    batch added by ``jax.vmap``.
    """
    g = jnp.array([0.0, 0.0, -9.81], gyro.dtype)

    def one(q, p, v, w, a):
        def body(carry, x):
            q, p, v = carry
            wk, ak, h = x
            acc = _quat_rotate(q, ak) + g
            p = p + h * v + 0.5 * h * h * acc
            v = v + h * acc
            q = _quat_mul(q, _quat_exp(h * wk))
            return (q, p, v), None

        return jax.lax.scan(body, (q, p, v), (w, a, dt))[0]

    return jax.vmap(one)(q0, p0, v0, gyro, accel)


# --------------------------------------------------------------------------- one case


def build(case: dict, T: int | None = None):
    """``(function to jit, its arguments)`` for ``case`` (optionally with T samples instead)."""
    B, T = case["B"], T or case["T"]
    x = make_inputs(B, T, case["dtype"])
    scheme, jac = case["scheme"], case["jac"]
    if case["kind"] == "mean":
        f = jaximu.propagate if case["save"] == "all" else jaximu.propagate_final
        kw = dict(omega_coriolis=EARTH_48) if case.get("rotating") else {}
        if case.get("lever"):
            kw["body_P_sensor"] = LEVER_POSE

        kw["attitude"] = case.get("attitude", "quaternion")

        def fn(s, g, a, h):
            return f(s, g, a, h, scheme, **kw)

        if case.get("vmap"):  # one trajectory per call, mapped; dt shared
            fn = jax.vmap(fn, in_axes=(0, 0, 0, None))
        return fn, (x["state"], x["gyro"], x["accel"], x["dt"])
    if case["kind"] == "cov":
        if case["save"] == "all":
            f = jaximu.propagate_covariance
        else:
            f = jaximu.propagate_covariance_final

        kw = dict(omega_coriolis=EARTH_48) if case.get("rotating") else {}
        if case.get("lever"):
            kw["body_P_sensor"] = LEVER_POSE

        kw["attitude"] = case.get("attitude", "quaternion")

        def fn(s, P, g, a, h):
            return f(s, P, g, a, h, NOISE, scheme, jacobians=jac, **kw)

        if case.get("vmap"):
            fn = jax.vmap(fn, in_axes=(0, None, 0, 0, None))
        return fn, (x["state"], x["P0"], x["gyro"], x["accel"], x["dt"])
    s = x["state"]
    return baseline_final, (s.q, s.p, s.v, x["gyro"], x["accel"], x["dt"])


def _all_finite(tree) -> bool:
    leaves = jax.tree_util.tree_leaves(tree)
    return all(bool(np.isfinite(np.asarray(leaf)).all()) for leaf in leaves)


def lane_mesh():
    """With ``--devices N``: the mesh of the N CPU devices, one ``Auto`` axis. Under it
    jaximu's kernels split their lanes over the devices (docs/guide/gpu.md)."""
    if DEVICES < 2:
        return None
    return jax.make_mesh((DEVICES,), ("lanes",), axis_types=(jax.sharding.AxisType.Auto,))


def place(args, B: int, mesh):
    """The arguments as a user of the mesh holds them: batch-leading arrays split over the
    devices (when they divide the batch), the rest replicated."""
    if mesh is None:
        return args
    P = jax.sharding.PartitionSpec
    split = jax.sharding.NamedSharding(mesh, P("lanes"))
    whole = jax.sharding.NamedSharding(mesh, P())

    def put(x):
        lanes = jnp.ndim(x) >= 1 and x.shape[0] == B and B % DEVICES == 0
        return jax.device_put(x, split if lanes else whole)

    return jax.tree_util.tree_map(put, args)


def measure(case: dict, reps: int, min_time: float, max_reps: int = 50) -> dict:
    """Compile ahead of time, then run ≥ ``reps`` times (more while under ``min_time`` s)."""
    mesh = lane_mesh()
    if mesh is not None:
        with jax.set_mesh(mesh):
            return _measure(case, reps, min_time, max_reps, mesh)
    return _measure(case, reps, min_time, max_reps, None)


def _measure(case: dict, reps: int, min_time: float, max_reps: int, mesh) -> dict:
    fn, args = build(case)
    args = place(args, case["B"], mesh)
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    lowered = jitted.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    try:
        xla_bytes = int(compiled.memory_analysis().peak_memory_in_bytes)
    except Exception:  # not every backend / version reports it
        xla_bytes = None
    runs, out = [], None
    while len(runs) < max_reps and (len(runs) < reps or sum(runs) < min_time):
        out = None  # free the previous output before the next run
        t = time.perf_counter()
        out = compiled(*args)
        jax.block_until_ready(out)
        runs.append(time.perf_counter() - t)
    best = min(runs)
    res = dict(
        status="ok",
        lower_s=t1 - t0,
        compile_s=t2 - t0,  # trace + lower + XLA compile
        first_call_s=t2 - t0 + runs[0],
        run_s=best,
        runs_s=runs,
        samples_per_s=case["B"] * case["T"] / best,
        xla_peak_bytes=xla_bytes,
        finite=_all_finite(out),
    )
    if case["kind"] == "baseline":
        # The reference must compute what the engine computes: compare final states.
        q_b, p_b, _ = out
        x = make_inputs(case["B"], case["T"], case["dtype"])
        eng = jax.jit(lambda s, g, a, h: jaximu.propagate_final(s, g, a, h, "euler"))(
            x["state"], x["gyro"], x["accel"], x["dt"]
        )
        dp = float(jnp.max(jnp.abs(eng.p - p_b)))
        scale = float(jnp.max(jnp.abs(eng.p)))
        dq = float(jnp.max(jnp.minimum(jnp.abs(eng.q - q_b).max(-1), jnp.abs(eng.q + q_b).max(-1))))
        res["check"] = dict(max_abs_dp_m=dp, max_abs_p_m=scale, max_abs_dq=dq)
    del out
    return res


def probe_run_time(case: dict, t_probe: int) -> tuple[float, float]:
    """Predict the run time of ``case`` from one run with only ``t_probe`` steps.

    Returns ``(predicted run s at the full T, probe compile s)``. The per-step cost of the
    scan does not depend on T, so a short probe predicts the full run.
    """
    fn, args = build(case, T=t_probe)
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    t = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    return (time.perf_counter() - t) * case["T"] / t_probe, compile_s


# --------------------------------------------------------------------------- subprocess mode


class CpuMeter:
    """CPU time that *other* processes used while we ran: a check that the machine was quiet.

    ``/proc/stat`` gives the busy time of the whole machine; this process and its waited-for
    children are subtracted. Returns the share of all CPUs (0..1) used by others, or None.
    """

    def __init__(self):
        self.start = self._read()

    @staticmethod
    def _read():
        try:
            fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:9]
        except (OSError, IndexError):
            return None
        v = [int(x) for x in fields]
        busy = (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")
        own = 0.0
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
            r = resource.getrusage(who)
            own += r.ru_utime + r.ru_stime
        return busy, own, time.perf_counter()

    def other_share(self):
        end = self._read()
        if self.start is None or end is None:
            return None
        busy, own, wall = (e - s for e, s in zip(end, self.start))
        ncpu = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        if wall <= 0:
            return None
        return min(1.0, max(0.0, (busy - own) / (wall * (ncpu or 1))))


def max_rss_bytes() -> int:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r if sys.platform == "darwin" else r * 1024  # Linux reports KiB


def worker(spec: dict) -> None:
    """``--worker``: run one case (or ``idle``) in this fresh process; print a JSON result."""
    if spec.get("kind") == "idle":
        jax.block_until_ready(jnp.zeros(3) + 1)
        res = dict(status="ok")
    else:
        res = measure(spec["case"], spec["reps"], spec["min_time"])
    res["max_rss_bytes"] = max_rss_bytes()
    print("@@RESULT " + json.dumps(res), flush=True)


def run_in_subprocess(payload: dict, timeout: float) -> dict:
    cmd = (
        [
            sys.executable,
            str(Path(__file__).resolve()),
            "--devices",
            str(DEVICES),
            "--vector-width",
            str(VECTOR_WIDTH),
        ]
        + (["--no-loop-unrolling"] if NO_UNROLL else [])
        + ["--worker", json.dumps(payload)]
    )
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return dict(status="failed", reason=f"subprocess exceeded {timeout:.0f} s")
    for line in p.stdout.splitlines():
        if line.startswith("@@RESULT "):
            return json.loads(line[len("@@RESULT ") :])
    tail = (p.stderr.strip().splitlines() or ["no output"])[-1]
    return dict(status="failed", reason=f"subprocess rc {p.returncode}: {tail}")


# --------------------------------------------------------------------------- machine info


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def mem_total_gb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def git_revision() -> str | None:
    """Git revision of the imported jaximu, ``+dirty`` if its package folder has changes."""
    pkg = Path(jaximu.__file__).resolve().parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=pkg, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "."],
            cwd=pkg,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return (rev + ("+dirty" if dirty else "")) or None
    except (OSError, subprocess.SubprocessError):
        return None


def machine_info() -> dict:
    dev = jax.devices()[0]
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = None
    return dict(
        cpu_model=cpu_model(),
        cpu_count=os.cpu_count(),
        cpus_usable=affinity,
        mem_total_gb=mem_total_gb(),
        hostname=socket.gethostname(),
        platform=platform.platform(),
        python=platform.python_version(),
        jax=jax.__version__,
        jaxlib=getattr(__import__("jaxlib"), "__version__", None),
        numpy=np.__version__,
        jaximu=jaximu.__version__,
        jaximu_git=git_revision(),
        backend=jax.default_backend(),
        device_kind=dev.device_kind,
        device_count=jax.device_count(),
        xla_flags=os.environ.get("XLA_FLAGS"),
    )


def machine_slug(info: dict) -> str:
    """``<cpu model>-<n>cpu`` (e.g. ``amd-epyc-2cpu``); the hostname if the CPU is unknown;
    on an accelerator its device kind (e.g. ``nvidia-h100-80gb-hbm3``)."""
    model = info["cpu_model"]
    if info.get("backend", "cpu") != "cpu":
        base = info["device_kind"] or info["backend"]
    elif not model or model == "unknown":
        base = info["hostname"] or "unknown"
    else:
        base = re.sub(r"\((r|tm)\)|\bcpu\b|\bprocessor\b|@.*$", "", model, flags=re.I)
        base = f"{base}-{info['cpus_usable'] or info['cpu_count']}cpu"
    return re.sub(r"[^a-z0-9]+", "-", base.lower()).strip("-")


# --------------------------------------------------------------------------- reporting


def fmt_rate(x: float) -> str:
    if x >= 1e6:
        return f"{x / 1e6:.2f} M"
    return f"{x / 1e3:.1f} k"


def fmt_bytes(b) -> str:
    if b is None:
        return ""
    mb = b / 2**20
    return f"{mb:.1f}" if mb < 10 else f"{mb:.0f}"


def sort_key(r: dict):
    c = r["case"]
    return (0 if c["section"] == "mean" else 1, CASE_ORDER.index(c["name"]), c["dtype"], r["order"])


def table(results: list[dict], rss: bool) -> str:
    mem_col = "max RSS MB" if rss else "XLA peak MB"
    lines = [
        "| case | dtype | B×T | samples/s | run ms | compile s | first call s | "
        f"{mem_col} | note |",
        "|---|---|---|--:|--:|--:|--:|--:|---|",
    ]
    for r in sorted(results, key=sort_key):
        c = r["case"]
        size = f"{c['B']}×{c['T']}"
        if r["status"] != "ok":
            lines.append(
                f"| {c['name']} | {c['dtype']} | {size} | {r['status']} | | | | | {r['reason']} |"
            )
            continue
        note = []
        if "check" in r:
            ck = r["check"]
            note.append(
                f"vs engine: max abs Δp {ck['max_abs_dp_m']:.1e} m "
                f"(|p| up to {ck['max_abs_p_m']:.3g} m), Δq {ck['max_abs_dq']:.1e}"
            )
        busy = r.get("other_cpu_share")
        if busy is not None and busy > BUSY_WARN:
            note.append(f"other processes used {busy:.0%} of the CPUs")
        if not r["finite"]:
            note.append("NON-FINITE OUTPUT")
        mem = r.get("max_rss_bytes") if rss else r.get("xla_peak_bytes")
        lines.append(
            f"| {c['name']} | {c['dtype']} | {size} | {fmt_rate(r['samples_per_s'])} | "
            f"{r['run_s'] * 1e3:.1f} | {r['compile_s']:.2f} | {r['first_call_s']:.2f} | "
            f"{fmt_bytes(mem)} | {'; '.join(note)} |"
        )
    return "\n".join(lines)


def target_summary(results: list[dict]) -> tuple[str, dict]:
    out, summary = [], {}
    ok = [r for r in results if r["status"] == "ok"]
    for key, label, target in (
        ("mean", "mean-only", TARGET_MEAN),
        ("cov", "with covariance", TARGET_COV),
    ):
        cands = [
            r
            for r in ok
            if r["case"]["kind"] == key and r["case"]["dtype"] == "float32" and r["case"]["B"] > 1
        ]
        if not cands:
            continue
        best = max(cands, key=lambda r: r["samples_per_s"])
        c, rate = best["case"], best["samples_per_s"]
        ratio = rate / target
        verdict = "meets target" if ratio >= 1 else "below target"
        out.append(
            f"- {label}: best {fmt_rate(rate)}samples/s ({c['name']}, {c['B']}×{c['T']}) "
            f"vs target ≥ {fmt_rate(target)}samples/s: ratio {ratio:.2f} ({verdict})"
        )
        summary[key] = dict(
            target=target,
            best=rate,
            ratio=ratio,
            meets=ratio >= 1,
            case=c["name"],
            B=c["B"],
            T=c["T"],
        )
    base = [r for r in ok if r["case"]["kind"] == "baseline"]
    for b in base:
        c = b["case"]
        same = (c["B"], c["T"], c["dtype"])
        eng = [
            r
            for r in ok
            if r["case"]["name"] == "mean euler final"
            and (r["case"]["B"], r["case"]["T"], r["case"]["dtype"]) == same
        ]
        if eng:
            sp = eng[0]["samples_per_s"] / b["samples_per_s"]
            out.append(
                f"- engine vs naive vmap(scan) baseline ({c['B']}×{c['T']} {c['dtype']}, "
                f"final only): {fmt_rate(eng[0]['samples_per_s'])} vs "
                f"{fmt_rate(b['samples_per_s'])}samples/s: {sp:.2f}×"
            )
            summary["baseline_speedup"] = sp

    def ratios(key, partner_name, against, target):
        """Each case with ``partner_name(case)`` measured at the same size: rate ratio."""
        for r in ok:
            c = r["case"]
            name = partner_name(c)
            if name is None:
                continue
            same = [
                x
                for x in ok
                if x["case"]["name"] == name
                and (x["case"]["B"], x["case"]["T"], x["case"]["dtype"])
                == (c["B"], c["T"], c["dtype"])
            ]
            if same:
                ratio = r["samples_per_s"] / same[0]["samples_per_s"]
                out.append(
                    f"- {c['name']} ({c['B']}×{c['T']} {c['dtype']}): "
                    f"{fmt_rate(r['samples_per_s'])}samples/s, {ratio:.2f}× {against} "
                    f"(target ≥ {target}×)"
                )
                summary.setdefault(key, {})[f"{c['name']} {c['B']}x{c['T']} {c['dtype']}"] = ratio

    # jax.vmap against the same work passed as leading axes
    ratios(
        "vmap_ratio",
        lambda c: c["name"][: -len(" vmap")] if c.get("vmap") else None,
        "leading axes",
        0.8,
    )
    # one long recording (time chunks side by side) against a batch of the same work: the
    # final covariance against 1024 × 1000, every covariance stored against 1024 × 200
    for r in ok:
        c = r["case"]
        if (
            c["kind"] != "cov"
            or c["B"] != 1
            or c.get("vmap")
            or c.get("rotating")
            or c.get("lever")
            or c.get("attitude", "quaternion") != "quaternion"
        ):
            continue
        size, target = ((1024, 200), 0.5) if c["save"] == "all" else ((1024, 1000), 0.8)
        same = [
            x
            for x in ok
            if x["case"]["name"] == c["name"]
            and (x["case"]["B"], x["case"]["T"], x["case"]["dtype"]) == size + (c["dtype"],)
        ]
        if same:
            ratio = r["samples_per_s"] / same[0]["samples_per_s"]
            out.append(
                f"- one recording: {c['name']} ({c['B']}×{c['T']} {c['dtype']}): "
                f"{fmt_rate(r['samples_per_s'])}samples/s, compile "
                f"{r['compile_s']:.2f} s; {ratio:.2f}× the batch {size[0]}×{size[1]} "
                f"(target ≥ {target}×)"
            )
            summary.setdefault("one_recording_ratio", {})[
                f"{c['name']} {c['B']}x{c['T']} {c['dtype']}"
            ] = ratio
    # autodiff Jacobians against the closed forms, same scheme and size
    ratios(
        "autodiff_ratio",
        lambda c: (
            c["name"].replace("autodiff", "analytic")
            if c["kind"] == "cov" and c["jac"] == "autodiff" and not c.get("vmap")
            else None
        ),
        "analytic",
        0.5,
    )
    return "\n".join(out), summary


def check(
    results: list[dict], baseline_path: Path, compile_fails: bool = False
) -> tuple[str, list[str]]:
    """This run against an earlier run's JSON: per case measured by both, the rate and
    compile-time ratios. Returns the report and the regressions (``--check``): run rates
    more than :data:`RATE_TOLERANCE` below the baseline's, and with ``compile_fails``
    compile times over :data:`COMPILE_LIMIT` times the baseline's."""
    base = json.loads(Path(baseline_path).read_text())
    key = lambda c: (c["name"], c["dtype"], c["B"], c["T"])  # noqa: E731
    old = {key(c): c for c in base["cases"] if c.get("status") == "ok"}
    lines, worse, slow_compiles, rates, compiles = [], [], [], [], []
    for r in sorted(results, key=sort_key):
        c = r["case"]
        label = f"{c['name']} {c['dtype']} {c['B']}×{c['T']}"
        if r["status"] != "ok":
            continue
        o = old.get(key(c))
        if o is None:
            lines.append(f"  new   {label}: no baseline")
            continue
        rate = r["samples_per_s"] / o["samples_per_s"]
        comp = r["compile_s"] / o["compile_s"]
        rates.append(rate)
        compiles.append(comp)
        bad = []
        if rate < 1 - RATE_TOLERANCE:
            bad.append(f"run rate {rate:.2f}× the baseline's")
        if comp > COMPILE_LIMIT:
            slow_compiles.append(label)
            bad.append(
                f"compile {comp:.2f}× the baseline's ({r['compile_s']:.2f} s against "
                f"{o['compile_s']:.2f} s)"
            )
        if rate < 1 - RATE_TOLERANCE or (compile_fails and comp > COMPILE_LIMIT):
            worse.append(label)
        tag = "WORSE" if label in worse else "slow compile" if bad else "ok   "
        lines.append(
            f"  {tag} {label}: rate {rate:.2f}×, compile {comp:.2f}×"
            + (f" -- {'; '.join(bad)}" if bad else "")
        )
    if rates:
        lines.append(
            f"  {len(rates)} cases compared: rate ratio median {np.median(rates):.2f} "
            f"(min {min(rates):.2f}), compile ratio median {np.median(compiles):.2f} "
            f"(max {max(compiles):.2f}); {len(slow_compiles)} over the compile limit; "
            f"{len(worse)} regression(s)"
        )
    return "\n".join(lines), worse


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    # allow_abbrev=False: --devices, --vector-width and --no-loop-unrolling are read from
    # sys.argv by their exact names before JAX starts
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke test (< 1 min)")
    ap.add_argument("--only", choices=("mean", "cov"), help="run only one group of cases")
    ap.add_argument("--reps", type=int, default=3, help="timed runs per case, at least (default 3)")
    ap.add_argument(
        "--min-time",
        type=float,
        default=0.3,
        help="keep timing a fast case until its runs add up to this many s (default 0.3)",
    )
    ap.add_argument(
        "--max-case-s",
        type=float,
        default=60.0,
        help="skip a case predicted to take longer than this many s (compile + runs; default 60)",
    )
    ap.add_argument(
        "--rss",
        action="store_true",
        help="run every case in its own process and report its max RSS (slower)",
    )
    ap.add_argument("--out", type=Path, help="JSON output path (default benchmarks/results/...)")
    ap.add_argument(
        "--first",
        type=int,
        default=1,
        help="start at this case number (the [N/...] printed), to finish a run that was cut",
    )
    ap.add_argument(
        "--deadline",
        type=float,
        help="start no case after this many s and write the cases done (a lent device's time)",
    )
    ap.add_argument(
        "--devices",
        type=int,
        default=1,
        help="split the CPU into this many JAX devices (one per core) and run "
        "every case under a mesh of them, inputs split over the batch "
        "(default 1: JAX's default single CPU device)",
    )
    ap.add_argument(
        "--vector-width",
        type=int,
        default=0,
        choices=(0, 128, 256, 512),
        help="XLA:CPU's preferred vector width in bits "
        "(--xla_cpu_prefer_vector_width in XLA_FLAGS; default 0: XLA's own, "
        "256)",
    )
    ap.add_argument(
        "--no-loop-unrolling",
        action="store_true",
        help="XLA:CPU compiles without LLVM loop unrolling "
        "(xla_cpu_disable_loop_unrolling in XLA_FLAGS' "
        "--xla_backend_extra_options; docs/guide/performance.md, "
        '"Compile time")',
    )
    ap.add_argument(
        "--check",
        type=Path,
        metavar="BASELINE",
        help="exit 1 if a case BASELINE (an earlier run's JSON) also measured runs "
        "more than 30%% slower",
    )
    ap.add_argument(
        "--check-compile",
        action="store_true",
        help="with --check: a compile time over 1.5× the baseline's fails too",
    )
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(json.loads(args.worker))
        return 0

    t_start = time.perf_counter()
    info = machine_info()
    cases, notes = plan(args.quick, args.only)
    run_meter = CpuMeter()
    print(
        f"jaximu {jaximu.__version__} propagation benchmark: {info['cpu_model']}, "
        f"{info['cpus_usable'] or info['cpu_count']} CPUs, jax {info['jax']} "
        f"({info['backend']}, {info['device_kind']}, {info['device_count']} device(s)"
        f"{', lanes split over a mesh of them' if DEVICES > 1 else ''}); {len(cases)} cases"
        f"{' (quick)' if args.quick else ''}",
        file=sys.stderr,
    )

    idle_rss = None
    if args.rss:
        idle = run_in_subprocess(dict(kind="idle"), timeout=120)
        idle_rss = idle.get("max_rss_bytes")
        notes.append(
            f"max RSS is the whole process (Python + JAX + inputs + outputs); an idle "
            f"process after `import jax, jaximu` peaks at {fmt_bytes(idle_rss)} MB."
        )

    if args.first > 1:
        notes.append(f"cases 1-{args.first - 1} not run here (--first {args.first})")
    results = []
    for i, case in enumerate(cases):
        if i + 1 < args.first:
            continue
        if args.deadline is not None and time.perf_counter() - t_start > args.deadline:
            print(f"deadline: cases {i + 1}-{len(cases)} not run", file=sys.stderr, flush=True)
            notes.append(f"cases {i + 1}-{len(cases)} not run (--deadline {args.deadline:g} s)")
            break
        label = f"[{i + 1}/{len(cases)}] {case['name']} {case['dtype']} {case['B']}×{case['T']}"
        print(label + " ...", end="", file=sys.stderr, flush=True)
        family = {k: v for k, v in case.items() if k not in ("B", "T")}
        # Predict the run time from a smaller size of the same case; if it may be long,
        # measure a short probe (same B, few steps) and skip the case when over budget.
        prior = [
            r
            for r in results
            if r["status"] == "ok"
            and {k: v for k, v in r["case"].items() if k not in ("B", "T")} == family
        ]
        skip_reason = None
        meter = CpuMeter()
        if prior:
            rate = prior[-1]["samples_per_s"]
            guess = args.reps * case["B"] * case["T"] / rate + prior[-1]["compile_s"]
            if guess > args.max_case_s / 2:
                t_probe = max(2, case["T"] // 20)
                run_s, probe_compile = probe_run_time(case, t_probe)
                predicted = args.reps * run_s + probe_compile
                if predicted > args.max_case_s:
                    skip_reason = (
                        f"skipped: predicted {predicted:.0f} s ({args.reps} runs × "
                        f"{run_s:.1f} s, from a {t_probe}-step probe) > "
                        f"{args.max_case_s:.0f} s budget; raise --max-case-s to run it"
                    )
        if skip_reason:
            res = dict(status="skipped", reason=skip_reason)
        elif args.rss:
            res = run_in_subprocess(
                dict(case=case, reps=args.reps, min_time=args.min_time),
                timeout=max(600.0, 10 * args.max_case_s),
            )
        else:
            res = measure(case, args.reps, args.min_time)
        res.update(case=case, order=i, other_cpu_share=meter.other_share())
        results.append(res)
        if res["status"] == "ok":
            print(
                f" {fmt_rate(res['samples_per_s'])}samples/s, run {res['run_s'] * 1e3:.1f} ms, "
                f"compile {res['compile_s']:.2f} s",
                file=sys.stderr,
                flush=True,
            )
        else:
            print(f" {res['reason']}", file=sys.stderr, flush=True)

    elapsed = time.perf_counter() - t_start
    other = run_meter.other_share()
    summary_text, summary = target_summary(results)
    print()
    print(table(results, args.rss))
    print()
    print(
        f"Run time: best of ≥ {args.reps} runs of the compiled function, compilation "
        "excluded; compile s: trace + lower + XLA compile; first call s: compile + first run."
    )
    print(
        "Memory: "
        + (
            "max RSS of the case's own process."
            if args.rss
            else "XLA's buffer estimate (arguments + outputs + temporaries) of the compiled "
            "function; process RSS is not measured (use --rss)."
        )
    )
    for n in notes:
        print(f"Note: {n}")
    if summary_text:
        print()
        print(
            "Targets (2-core CPU, float32, batched B > 1)"
            + (" -- quick sizes, not representative:" if args.quick else ":")
        )
        print(summary_text)
    print()
    print(
        f"Total benchmark time {elapsed:.0f} s"
        + ("." if other is None else f"; other processes used {other:.0%} of the CPUs.")
    )
    if other is not None and other > BUSY_WARN:
        print(
            "Warning: the machine was not idle; run and compile times are inflated "
            "(see the note column)."
        )

    out = args.out
    if out is None:
        suffix = (
            ("-quick" if args.quick else "")
            + (f"-{args.only}" if args.only else "")
            + (f"-{args.devices}dev" if args.devices > 1 else "")
            + (f"-vw{args.vector_width}" if args.vector_width else "")
            + ("-nounroll" if NO_UNROLL else "")
        )
        out = RESULTS_DIR / f"propagation-{machine_slug(info)}{suffix}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = dict(
        benchmark="jaximu propagation throughput",
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        machine=info,
        settings=dict(
            quick=args.quick,
            only=args.only,
            reps=args.reps,
            min_time_s=args.min_time,
            max_case_s=args.max_case_s,
            rss=args.rss,
            dt=DT,
            gyro_std=GYRO_STD,
            accel_std=ACCEL_STD,
            noise="ImuNoise.euroc()",
            attitude="quaternion",
            devices=args.devices,
            vector_width=args.vector_width or None,
            loop_unrolling=NO_UNROLL_OPTION not in os.environ.get("XLA_FLAGS", ""),
            argv=sys.argv[1:],
        ),
        definitions=dict(
            samples_per_s="B*T / run_s",
            run_s="best of >= reps runs of the AOT-compiled jax.jit function (block_until_ready)",
            compile_s="jax.jit(f).lower(*args).compile() wall time (trace + lower + compile)",
            first_call_s="compile_s + the first run",
            xla_peak_bytes="compiled.memory_analysis().peak_memory_in_bytes",
            max_rss_bytes="ru_maxrss of the case's own process (--rss only)",
            other_cpu_share="share of all CPUs used by other processes during the case "
            "(from /proc/stat minus this process and its children)",
        ),
        idle_process_max_rss_bytes=idle_rss,
        notes=notes,
        targets=summary,
        total_s=elapsed,
        other_cpu_share=other,
        cases=[
            {**r["case"], **{k: v for k, v in r.items() if k not in ("case", "order")}}
            for r in sorted(results, key=sort_key)
        ],
    )
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"Wrote {out}", file=sys.stderr)
    if args.check:
        report, worse = check(results, args.check, args.check_compile)
        print(
            f"\nRegression check against {args.check} (run rate tolerance "
            f"{RATE_TOLERANCE:.0%}; compile time limit {COMPILE_LIMIT}×"
            f"{'' if args.check_compile else ', reported'}):"
        )
        print(report)
        return 1 if worse else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
