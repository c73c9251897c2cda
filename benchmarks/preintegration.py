"""Preintegration throughput: jaximu (sequential and parallel) against GTSAM's Python API.

    python benchmarks/preintegration.py           # ~2-4 min on a 2-core CPU
    python benchmarks/preintegration.py --quick   # small sizes, < 1 min

Workloads (real EuRoC MAV samples, tiled; noise = EuRoC ADIS16448 densities; covariance
and bias Jacobians always computed):

* ``long``:    one window of 10^5 samples (500 s at 200 Hz);
* ``windows``: 4096 windows of 200 samples (1 s each), batched; also with
  ``jacobians="autodiff"`` and with VINS-Mono's midpoint (closed form and autodiff);
* ``factors``: ``predict``, ``residual``, ``whitened_residual`` and the gradient of its
  squared norm on the 4096 windows' measurements (windows/s).

jaximu computes the deltas, all five bias Jacobians (the full 15×15 transition), the 9×9
covariance and the 15×15 one with the bias random walk. The rows "auto, 9×9 + bias
Jacobians" time a jitted program that returns only the deltas, the 9×9 covariance and the
transition (what the C++ reference, GTSAM's Manifold class, Basalt and VINS-Mono compute):
the 15×15 recursion is then not run (``jaximu.engine._batching``'s dead-code rule); their numbers
are checked equal to the whole result's. The GTSAM baseline is
``PreintegratedImuMeasurementsManifold`` (9×9 covariance and bias Jacobians; the Manifold
class is the one that equals exact Euler preintegration) fed sample by sample from Python,
and ``PreintegratedCombinedMeasurementsManifold`` (15×15) for reference. Reported: samples/s
(run time excludes compilation), compile time apart, the ratio to GTSAM, and the agreement
of the deltas with GTSAM (max abs difference, float64 Euler), so a fast wrong answer shows.

Where g++ and Eigen are found, a C++/Eigen program of ours (``cpp/preintegrate_reference.cpp``,
built by ``cpp_reference.py``; one core, float64, 9×9 covariance and bias Jacobians) runs on
the same samples as the row "C++ Eigen reference (1 core)", with the ratio jaximu / C++.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

# (propagation reads --devices before JAX starts: one CPU device per core)
from propagation import (  # noqa: E402
    DEVICES,
    NO_UNROLL,
    VECTOR_WIDTH,
    lane_mesh,
    machine_info,
    machine_slug,
    place,
)

import jaximu  # noqa: E402
from jaximu.datasets import euroc_v1_02_segment  # noqa: E402

TARGETS = {"long": 5.0, "windows": 10.0}  # × GTSAM Manifold, float64


def make_inputs(n_long, n_windows, window_len, seed=0):
    seg = euroc_v1_02_segment()
    flight = slice(800, 3999)  # after take-off
    g, a = seg.gyro[flight], seg.accel[flight]
    reps = -(-n_long // len(g))
    long = (np.tile(g, (reps, 1))[:n_long], np.tile(a, (reps, 1))[:n_long], np.full(n_long, 0.005))
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, len(g) - window_len, size=n_windows)
    idx = starts[:, None] + np.arange(window_len)
    windows = (g[idx], a[idx], np.full((n_windows, window_len), 0.005))
    bias = (seg.b_g_gt[1000], seg.b_a_gt[1000])
    return long, windows, bias


def best_time(fn, reps=3, min_time=0.3):
    times = []
    while len(times) < reps or sum(times) < min_time:
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        if len(times) > 50:
            break
    return min(times)


# what the C++ reference, Basalt and VINS-Mono compute: the deltas, the 9×9 covariance and
# the bias Jacobians (the rows of the transition); a jitted program that reads only these
# does not compute the 15×15 cov15 (jaximu.engine._batching's dead-code rule)
NINE = ("delta_t", "delta_q", "delta_v", "delta_p", "cov", "transition")


def bench_jaximu(data, bias, dtype, method, scheme="euler", jacobians="analytic", fields=None):
    """``fields``: the result's fields the jitted program returns (``None``: the whole
    :class:`jaximu.Preintegrated`, ``cov15`` included)."""
    gyro, accel, dt = (jnp.asarray(x, dtype) for x in data)
    b = jaximu.ImuBias(jnp.asarray(bias[0], dtype), jnp.asarray(bias[1], dtype))
    noise = jaximu.ImuNoise.euroc()

    def run(g, a, d):
        pim = jaximu.preintegrate(g, a, d, b, noise, scheme, method, jacobians=jacobians)
        return pim if fields is None else {k: getattr(pim, k) for k in fields}

    fn = jax.jit(run)
    mesh = lane_mesh()  # --devices N: windows split over the devices, a long one's chunks too
    if mesh is not None:
        gyro, accel, dt = place((gyro, accel, dt), gyro.shape[0], mesh)
    with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(gyro, accel, dt))
        first = time.perf_counter() - t0
        run = best_time(lambda: fn(gyro, accel, dt))
    return out, run, max(first - run, 0.0)


def bench_gtsam(data, bias, combined=False):
    import gtsam

    gyro, accel, dt = data
    cls_p = gtsam.PreintegrationCombinedParams if combined else gtsam.PreintegrationParams
    params = cls_p.MakeSharedU(9.81)
    n = jaximu.ImuNoise.euroc()
    params.setGyroscopeCovariance(np.eye(3) * n.gyroscope_noise_density**2)
    params.setAccelerometerCovariance(np.eye(3) * n.accelerometer_noise_density**2)
    params.setIntegrationCovariance(np.zeros((3, 3)))
    if combined:
        params.setBiasAccCovariance(np.eye(3) * n.accelerometer_random_walk**2)
        params.setBiasOmegaCovariance(np.eye(3) * n.gyroscope_random_walk**2)
    cls = (
        gtsam.PreintegratedCombinedMeasurementsManifold
        if combined
        else gtsam.PreintegratedImuMeasurementsManifold
    )
    b = gtsam.imuBias.ConstantBias(np.asarray(bias[1]), np.asarray(bias[0]))
    batch = gyro.shape[:-2]
    gyro = gyro.reshape(-1, *gyro.shape[-2:])
    accel = accel.reshape(-1, *accel.shape[-2:])
    dt = np.broadcast_to(dt, gyro.shape[:-1]).reshape(-1, gyro.shape[-2])
    t0 = time.perf_counter()
    pims = []
    for w in range(gyro.shape[0]):
        pim = cls(params, b)
        gw, aw, dw = gyro[w], accel[w], dt[w]
        for k in range(gw.shape[0]):
            pim.integrateMeasurement(aw[k], gw[k], dw[k])
        pims.append(pim)
    elapsed = time.perf_counter() - t0
    last = pims[-1] if not batch else pims
    return last, elapsed


def main(argv=None):
    # allow_abbrev=False: --vector-width and --no-loop-unrolling are read from sys.argv
    # by their exact names before JAX starts (benchmarks/propagation.py)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--out", default=None, help="JSON output path")
    ap.add_argument(
        "--devices",
        type=int,
        default=1,
        help="split the CPU into this many JAX devices and run jaximu under a mesh "
        "of them (benchmarks/propagation.py --devices)",
    )
    ap.add_argument(
        "--vector-width",
        type=int,
        default=0,
        choices=(0, 128, 256, 512),
        help="XLA:CPU's preferred vector width in bits (benchmarks/propagation.py --vector-width)",
    )
    ap.add_argument(
        "--no-loop-unrolling",
        action="store_true",
        help="XLA:CPU compiles without LLVM loop unrolling "
        "(benchmarks/propagation.py --no-loop-unrolling)",
    )
    args = ap.parse_args(argv)
    n_long, n_win, w_len = (20_000, 512, 200) if args.quick else (100_000, 4096, 200)
    long, windows, bias = make_inputs(n_long, n_win, w_len)
    rows = []
    info = machine_info()
    print(
        f"# preintegration benchmark on {info['cpu_model']} ({info['cpu_count']} CPUs), "
        f"jax {jax.__version__}, {jax.default_backend()}",
        flush=True,
    )

    gtsam_rate = {}
    gtsam_out = {}
    try:
        import gtsam  # noqa: F401

        for name, data in (("long", long), ("windows", windows)):
            out, secs = bench_gtsam(data, bias)
            n = int(np.prod(data[0].shape[:-1]))
            gtsam_rate[name] = n / secs
            gtsam_out[name] = out
            rows.append(
                dict(
                    tool="gtsam Manifold (Python loop)",
                    workload=name,
                    dtype="float64",
                    method="-",
                    samples=n,
                    run_s=secs,
                    compile_s=0.0,
                    rate=n / secs,
                )
            )
            print(f"gtsam {name}: {n / secs / 1e6:.3f} M samples/s", flush=True)
        out, secs = bench_gtsam(long, bias, combined=True)
        rows.append(
            dict(
                tool="gtsam CombinedManifold (Python loop)",
                workload="long",
                dtype="float64",
                method="-",
                samples=n_long,
                run_s=secs,
                compile_s=0.0,
                rate=n_long / secs,
            )
        )
    except ImportError:
        print("gtsam is not installed: baseline skipped (pip install gtsam)", flush=True)

    # --- C++ Eigen reference (optional: needs g++ and Eigen; see cpp_reference.py) ---------
    from cpp_reference import run_cpp_reference  # same folder

    cpp_rate, basalt_rate, basalt_out = {}, {}, {}
    for name, data in (("long", long), ("windows", windows)):
        ref = run_cpp_reference(
            *data, *bias, jaximu.ImuNoise.euroc(), name, kernels=("blocked", "basalt")
        )
        if ref is None:
            break
        if "basalt" in ref["kernels"]:  # the peer itself (BASALT_HEADERS_DIR given)
            kb = ref["kernels"]["basalt"]
            basalt_rate[name], basalt_out[name] = kb["samples_per_s"], kb["result"]
            rows.append(
                dict(
                    tool="Basalt IntegratedImuMeasurement (1 core)",
                    workload=name,
                    dtype="float64",
                    method="basalt",
                    samples=ref["samples"],
                    run_s=kb["best_s"],
                    compile_s=0.0,
                    rate=kb["samples_per_s"],
                    us_per_sample=kb["us_per_sample"],
                    command=ref["command"],
                    compiler=ref["compiler"],
                )
            )
            print(
                f"Basalt {name}: {kb['samples_per_s'] / 1e6:.3f} M samples/s "
                f"({kb['us_per_sample']:.3f} µs/sample)",
                flush=True,
            )
        k = ref["kernels"]["blocked"]
        cpp_rate[name] = k["samples_per_s"]
        row = dict(
            tool="C++ Eigen reference (1 core)",
            workload=name,
            dtype="float64",
            method="blocked",
            samples=ref["samples"],
            run_s=k["best_s"],
            compile_s=0.0,
            rate=k["samples_per_s"],
            us_per_sample=k["us_per_sample"],
            command=ref["command"],
            compiler=ref["compiler"],
        )
        if name in gtsam_rate:
            row["ratio_to_gtsam"] = row["rate"] / gtsam_rate[name]
        if name in gtsam_out:  # the same comparison as the jaximu rows'
            res, ref_g = k["result"], gtsam_out[name]
            if name == "long":
                R = np.asarray(jaximu.so3.quat_to_matrix(res["delta_q"]))
                d = max(
                    np.abs(res["delta_p"] - ref_g.deltaPij()).max(),
                    np.abs(res["delta_v"] - ref_g.deltaVij()).max(),
                    np.abs(R - ref_g.deltaRij().matrix()).max(),
                )
            else:
                d = max(
                    np.abs(res["delta_p"][i] - ref_g[i].deltaPij()).max()
                    for i in range(0, len(ref_g), max(1, len(ref_g) // 16))
                )
            row["max_abs_diff_vs_gtsam"] = float(d)
        rows.append(row)
        print(
            f"C++ Eigen reference {name}: {k['samples_per_s'] / 1e6:.3f} M samples/s "
            f"({k['us_per_sample']:.3f} µs/sample)",
            flush=True,
        )
    # ------------------------------------------------------------------------------------------

    agreement, pim_f64 = {}, {}
    for dtype in (jnp.float64, jnp.float32):
        for name, data in (("long", long), ("windows", windows)):
            for method in ("auto", "sequential", "parallel"):  # auto: the default
                out, run, comp = bench_jaximu(data, bias, dtype, method)
                if (jnp.dtype(dtype), name, method) == (jnp.float64, "windows", "auto"):
                    pim = out  # the measurements of the factor rows below
                n = int(np.prod(data[0].shape[:-1]))
                tool = "jaximu" if DEVICES < 2 else f"jaximu ({DEVICES} CPU devices)"
                row = dict(
                    tool=tool,
                    workload=name,
                    dtype=jnp.dtype(dtype).name,
                    method=method,
                    samples=n,
                    run_s=run,
                    compile_s=comp,
                    rate=n / run,
                )
                if name in gtsam_rate:
                    row["ratio_to_gtsam"] = row["rate"] / gtsam_rate[name]
                if dtype == jnp.float64 and name in gtsam_out:
                    ref = gtsam_out[name]
                    if name == "long":
                        d = max(
                            np.abs(np.asarray(out.delta_p) - ref.deltaPij()).max(),
                            np.abs(np.asarray(out.delta_v) - ref.deltaVij()).max(),
                            np.abs(np.asarray(out.delta_R) - ref.deltaRij().matrix()).max(),
                        )
                    else:
                        d = max(
                            np.abs(np.asarray(out.delta_p[i]) - ref[i].deltaPij()).max()
                            for i in range(0, len(ref), max(1, len(ref) // 16))
                        )
                    row["max_abs_diff_vs_gtsam"] = float(d)
                    agreement[(name, method)] = float(d)
                rows.append(row)
                print(
                    f"jaximu {row['dtype']} {name} {method}: {row['rate'] / 1e6:.3f} M "
                    f"samples/s (compile {comp:.1f} s)",
                    flush=True,
                )
                if method != "auto":
                    continue
                # the C++ reference's outputs only (no cov15): the same numbers, checked
                nine, run9, comp9 = bench_jaximu(data, bias, dtype, method, fields=NINE)
                if dtype == jnp.float64:
                    pim_f64[name] = out
                for k in NINE:  # each field against its own scale
                    diff = float(jnp.max(jnp.abs(nine[k] - getattr(out, k))))
                    if diff > 1e-12 * float(jnp.max(jnp.abs(getattr(out, k)))):
                        raise AssertionError(
                            f"the 9×9 program's {k} differs from the whole result's by {diff:.2e}"
                        )
                row = dict(
                    row,
                    method="auto, 9×9 + bias Jacobians",
                    run_s=run9,
                    compile_s=comp9,
                    rate=n / run9,
                )
                if name in gtsam_rate:
                    row["ratio_to_gtsam"] = row["rate"] / gtsam_rate[name]
                rows.append(row)
                print(
                    f"jaximu {row['dtype']} {name} {row['method']}: "
                    f"{row['rate'] / 1e6:.3f} M samples/s (compile {comp9:.1f} s)",
                    flush=True,
                )

    # the other schemes and Jacobian options a user can pick, on the windows (defaults
    # otherwise): VINS-Mono's midpoint, and autodiff Jacobians (Euler's run its kernel;
    # the midpoint's exact derivatives run the generic recursion)
    for dtype in (jnp.float64, jnp.float32):
        for scheme, jac in (
            ("euler", "autodiff"),
            ("midpoint", "analytic"),
            ("midpoint", "autodiff"),
        ):
            out, run, comp = bench_jaximu(windows, bias, dtype, "auto", scheme, jac)
            n = int(np.prod(windows[0].shape[:-1]))
            tool = "jaximu" if DEVICES < 2 else f"jaximu ({DEVICES} CPU devices)"
            row = dict(
                tool=tool,
                workload="windows",
                dtype=jnp.dtype(dtype).name,
                method=f"auto, {scheme}, {jac}",
                scheme=scheme,
                jacobians=jac,
                samples=n,
                run_s=run,
                compile_s=comp,
                rate=n / run,
            )
            if "windows" in gtsam_rate:
                row["ratio_to_gtsam"] = row["rate"] / gtsam_rate["windows"]
            rows.append(row)
            print(
                f"jaximu {row['dtype']} windows {row['method']}: {row['rate'] / 1e6:.3f} M "
                f"samples/s (compile {comp:.1f} s)",
                flush=True,
            )

    # factors on the windows' measurements (float64): predict, residual, whitened residual
    # and the gradient of the whitened squared norm with respect to the states i, the
    # evaluations an optimiser repeats (rate: windows/s in the samples/s column)
    nw = pim.delta_t.shape[0]
    rng = np.random.default_rng(1)
    q = rng.normal(size=(nw, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s_i = jaximu.NavState(
        jnp.asarray(q), *(jnp.asarray(rng.normal(size=(nw, 3))) for _ in range(4))
    )
    s_j = jaximu.boxplus(jaximu.predict(s_i, pim), jnp.asarray(rng.normal(size=(nw, 15)) * 1e-3))
    factors = {
        "predict": lambda s: jaximu.predict(s, pim),
        "residual": lambda s: jaximu.residual(s, s_j, pim),
        "whitened_residual": lambda s: jaximu.whitened_residual(s, s_j, pim),
        "grad ‖whitened_residual‖²": jax.grad(
            lambda s: jnp.sum(jaximu.whitened_residual(s, s_j, pim) ** 2)
        ),
    }
    mesh = lane_mesh()  # the measurements closed over are sharded on it: run under it
    for name, f in factors.items():
        f = jax.jit(f)
        with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
            t0 = time.perf_counter()
            jax.block_until_ready(f(s_i))
            first = time.perf_counter() - t0
            run = best_time(lambda: f(s_i))
        tool = "jaximu" if DEVICES < 2 else f"jaximu ({DEVICES} CPU devices)"
        rows.append(
            dict(
                tool=tool,
                workload="factors",
                dtype="float64",
                method=name,
                samples=nw,
                run_s=run,
                compile_s=max(first - run, 0.0),
                rate=nw / run,
            )
        )
        print(f"jaximu factors {name}: {nw / run / 1e6:.3f} M windows/s", flush=True)

    print(
        "\n| tool | workload | dtype | method | samples/s | run ms | compile s | × GTSAM | "
        "max abs diff vs GTSAM |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = f"{r['ratio_to_gtsam']:.1f}" if "ratio_to_gtsam" in r else "-"
        diff = f"{r['max_abs_diff_vs_gtsam']:.1e}" if "max_abs_diff_vs_gtsam" in r else "-"
        print(
            f"| {r['tool']} | {r['workload']} ({r['samples']}) | {r['dtype']} | {r['method']} "
            f"| {r['rate'] / 1e6:.3f} M | {r['run_s'] * 1e3:.1f} | {r['compile_s']:.1f} | "
            f"{ratio} | {diff} |"
        )
    if gtsam_rate:
        print("\nTargets (float64, with covariance and bias Jacobians):")
        for name, target in TARGETS.items():
            best = max(
                (
                    r
                    for r in rows
                    if r["tool"].startswith("jaximu")
                    and r["workload"] == name
                    and r["dtype"] == "float64"
                ),
                key=lambda r: r["rate"],
            )
            ratio = best["ratio_to_gtsam"]
            verdict = "met" if ratio >= target else f"missed by {target / ratio:.1f}×"
            print(
                f"- {name}: {ratio:.1f}× GTSAM ({best['method']}), target {target:.0f}×: {verdict}"
            )
    # --- jaximu / C++ Eigen reference --------------------------------------------------------
    if cpp_rate:
        print(
            "\njaximu / C++ Eigen reference (one core, float64, blocked 9×9 covariance and "
            "bias Jacobians; > 1: jaximu faster):"
        )
        for r in rows:
            if r["tool"].startswith("jaximu") and r["workload"] in cpp_rate:
                r["ratio_to_cpp"] = r["rate"] / cpp_rate[r["workload"]]
                print(f"- {r['workload']} {r['dtype']} {r['method']}: {r['ratio_to_cpp']:.2f}")
    # --- jaximu / Basalt ---------------------------------------------------------------------
    if basalt_rate:
        # Basalt rotates each step's specific force by the half-step rotation, so its Δv, Δp
        # and their Jacobians differ from Euler's by O(|ω| h) relative; its ΔR and dR/dbg are
        # the same mathematics (checked to rounding here, a check of the frame conversion)
        from cpp_reference import agreement as cpp_agreement  # same folder

        print("\nBasalt vs jaximu float64 Euler (max abs diff / max |value|):")
        for name, res in basalt_out.items():
            agree = cpp_agreement(res, pim_f64[name])
            print(
                "- "
                + name
                + ": "
                + ", ".join(f"{f} {d / max(m, 1e-300):.1e}" for f, (d, m) in agree.items())
            )
            rot = max(agree[f][0] / agree[f][1] for f in ("delta_q", "dR_dbg"))
            if rot > 1e-9:
                raise AssertionError(
                    f"Basalt's rotation differs from jaximu's by {rot:.1e} "
                    f"({name}): the frame conversion is wrong"
                )
        print(
            "\njaximu / Basalt (Basalt on one core, float64; target ≥ 6× with covariance "
            "and bias Jacobians):"
        )
        for r in rows:
            if r["tool"].startswith("jaximu") and r["workload"] in basalt_rate:
                r["ratio_to_basalt"] = r["rate"] / basalt_rate[r["workload"]]
                if r["dtype"] == "float64" and r["method"].startswith("auto"):
                    print(
                        f"- {r['workload']} {r['dtype']} {r['method']}: {r['ratio_to_basalt']:.2f}"
                    )
    # ------------------------------------------------------------------------------------------
    out_path = args.out or os.path.join(
        os.path.dirname(__file__),
        "results",
        f"preintegration-{machine_slug(info)}{'-quick' if args.quick else ''}"
        f"{f'-{DEVICES}dev' if DEVICES > 1 else ''}"
        f"{f'-vw{VECTOR_WIDTH}' if VECTOR_WIDTH else ''}{'-nounroll' if NO_UNROLL else ''}.json",
    )
    os.makedirs(os.path.dirname(out_path), exist_ok=True)
    with open(out_path, "w") as f:
        json.dump(dict(machine=info, rows=rows), f, indent=1)
    print(f"\nwrote {out_path}")


if __name__ == "__main__":
    main()
