"""jaximu against its peers on the same workloads, in one run on one machine.

    pip install ".[bench]"                     # gtsam; for PyPose first a CPU torch
                                               # (docs/guide/performance.md)
    python benchmarks/peers.py                 # full sizes (~5 min on 2 cores)
    python benchmarks/peers.py --quick         # small sizes (~1 min)
    python benchmarks/peers.py --check benchmarks/results/peers-baseline-intel-xeon-2cpu.json

Workloads (EuRoC ADIS16448 noise densities; real EuRoC samples for preintegration):

* ``preint-long``:    preintegration with covariance, one sequence of 10^5 samples;
* ``preint-windows``: preintegration with covariance, 4096 windows × 200 samples;
* ``mean``:           mean-only propagation, 16384 trajectories × 200 samples;
* ``cov``:            propagation with the covariance, 1024 × 1000;
* ``montecarlo``:     Monte Carlo covariance, 10^4 runs × 1000 samples (GTSAM's
  ``ScenarioRunner.estimateCovariance`` as the peer).

Tools: jaximu (jit, compile time apart), GTSAM's Python API (``*Manifold`` classes fed
sample by sample; C++ inside), PyPose's ``IMUPreintegrator`` (torch, batched; 9×9
covariance, no bias Jacobians: it computes less), and a plain NumPy transcription (loop over
time, vectorised over the batch; Python loop over samples for the single sequence). Each row
has samples/s, the ratio of jaximu to the peer, compile time, the peak growth of the process's
resident memory during the case (sampled every 2 ms from ``/proc/self/statm``; jaximu's
includes XLA's compiler on the first call) and the
agreement with jaximu (max abs difference of the final position/Δp [m]), so a fast wrong
answer shows. Peers that are not installed are reported as skipped.

``--check BASELINE``: compares this run's ratios (jaximu over each peer; run-time ratios
measured in the same run, so machine speed cancels) with the baseline's and exits 1 if any is
more than 30% worse.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from preintegration import bench_gtsam as gtsam_preintegrate  # noqa: E402  (same folder)
from preintegration import make_inputs  # noqa: E402
from propagation import machine_info, machine_slug  # noqa: E402

import jaximu  # noqa: E402

NOISE = jaximu.ImuNoise.euroc()
DT = 0.005
TOLERANCE = 0.30  # --check: a ratio more than 30% below the baseline's is a regression


# --------------------------------------------------------------------------- measuring


class PeakRss:
    """Peak growth of this process's resident memory while the block runs [MB]."""

    def __enter__(self):
        self.page = os.sysconf("SC_PAGE_SIZE")
        self.base = self.peak = self._rss()
        self.stop = False
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()
        return self

    def _rss(self):
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self.page

    def _poll(self):
        while not self.stop:
            self.peak = max(self.peak, self._rss())
            time.sleep(0.002)

    def __exit__(self, *exc):
        self.stop = True
        self.thread.join()
        self.peak = max(self.peak, self._rss())
        self.mb = (self.peak - self.base) / 2**20


def measure(fn, reps=2):
    """``(best run s, compile-or-warm-up s, peak MB, output)``: the first call apart."""
    with PeakRss() as mem:
        t0 = time.perf_counter()
        out = fn()
        first = time.perf_counter() - t0
        runs = []
        for _ in range(reps):
            t0 = time.perf_counter()
            out = fn()
            runs.append(time.perf_counter() - t0)
    return min(runs), max(first - min(runs), 0.0), mem.mb, out


def block(x):
    return jax.block_until_ready(x)


# --------------------------------------------------------------------------- workloads


def numpy_exp(phi):
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors (Rodrigues)."""
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = np.zeros(phi.shape[:-1] + (3, 3), phi.dtype)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -phi[..., 2], phi[..., 1], -phi[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1 - th**2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    return np.eye(3, dtype=phi.dtype) + a * K + b * (K @ K)


def numpy_skew(v):
    K = np.zeros(v.shape[:-1] + (3, 3), v.dtype)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return K - np.swapaxes(K, -1, -2)


def numpy_preintegrate(gyro, accel, dt, cov=True):
    """Forster's Euler preintegration with the 9×9 covariance ``[θ, p, v]``, vectorised over
    leading axes, a loop over time: the plain NumPy baseline (no bias Jacobians)."""
    B = gyro.shape[:-2]
    R = np.broadcast_to(np.eye(3, dtype=gyro.dtype), B + (3, 3)).copy()
    v = np.zeros(B + (3,), gyro.dtype)
    p = np.zeros(B + (3,), gyro.dtype)
    P = np.zeros(B + (9, 9), gyro.dtype)
    qg = NOISE.gyroscope_noise_density**2
    qa = NOISE.accelerometer_noise_density**2
    for k in range(gyro.shape[-2]):
        h = dt[..., k, None]
        a = np.einsum("...ij,...j->...i", R, accel[..., k, :])
        dR = numpy_exp(gyro[..., k, :] * h)
        if cov:
            A = np.zeros(B + (9, 9), gyro.dtype)
            A[..., 0:3, 0:3] = np.swapaxes(dR, -1, -2)
            RaX = R @ numpy_skew(accel[..., k, :])
            hh = h[..., None]
            A[..., 3:6, 0:3] = -0.5 * RaX * hh**2
            A[..., 3:6, 3:6] = np.eye(3)
            A[..., 3:6, 6:9] = np.eye(3) * hh
            A[..., 6:9, 0:3] = -RaX * hh
            A[..., 6:9, 6:9] = np.eye(3)
            G = np.zeros(B + (9, 6), gyro.dtype)
            G[..., 0:3, 0:3] = np.eye(3) * hh  # Jr(ω h) h ≈ h I at these rates
            G[..., 3:6, 3:6] = 0.5 * R * hh**2
            G[..., 6:9, 3:6] = R * hh
            Q = np.concatenate([np.full(3, qg), np.full(3, qa)]) / h
            P = A @ P @ np.swapaxes(A, -1, -2) + (G * Q[..., None, :]) @ np.swapaxes(G, -1, -2)
        p = p + v * h + 0.5 * a * h**2
        v = v + a * h
        R = R @ dR
    return R, p, v, P


def numpy_propagate(gyro, accel, dt, g, cov=False):
    """World-frame Euler propagation from the identity (mean; optionally 15×15 covariance)."""
    B = gyro.shape[:-2]
    R = np.broadcast_to(np.eye(3, dtype=gyro.dtype), B + (3, 3)).copy()
    v = np.zeros(B + (3,), gyro.dtype)
    p = np.zeros(B + (3,), gyro.dtype)
    P = np.broadcast_to(np.eye(15, dtype=gyro.dtype) * 1e-6, B + (15, 15)).copy() if cov else None
    var = np.concatenate(
        [
            np.full(3, NOISE.gyroscope_noise_density**2),
            np.full(3, NOISE.accelerometer_noise_density**2),
            np.full(3, NOISE.gyroscope_random_walk**2),
            np.full(3, NOISE.accelerometer_random_walk**2),
        ]
    ).astype(gyro.dtype)
    for k in range(gyro.shape[-2]):
        h = dt[k]
        a = np.einsum("...ij,...j->...i", R, accel[..., k, :]) + g
        dR = numpy_exp(gyro[..., k, :] * h)
        if cov:
            F = np.broadcast_to(np.eye(15, dtype=gyro.dtype), B + (15, 15)).copy()
            F[..., 0:3, 0:3] = np.swapaxes(dR, -1, -2)
            F[..., 0:3, 9:12] = -np.eye(3) * h
            RaX = R @ numpy_skew(accel[..., k, :])
            F[..., 3:6, 0:3] = -0.5 * RaX * h * h
            F[..., 3:6, 6:9] = np.eye(3) * h
            F[..., 3:6, 12:15] = -0.5 * R * h * h
            F[..., 6:9, 0:3] = -RaX * h
            F[..., 6:9, 12:15] = -R * h
            G = np.zeros(B + (15, 12), gyro.dtype)
            G[..., 0:3, 0:3] = -np.eye(3) * h
            G[..., 3:6, 3:6] = -0.5 * R * h * h
            G[..., 6:9, 3:6] = -R * h
            G[..., 9:12, 6:9] = np.eye(3) * h
            G[..., 12:15, 9:12] = np.eye(3) * h
            P = F @ P @ np.swapaxes(F, -1, -2) + (G * (var / h)) @ np.swapaxes(G, -1, -2)
        p = p + v * h + 0.5 * a * h * h
        v = v + a * h
        R = R @ dR
    return R, p, v, P


def pypose_run(gyro, accel, dt, torch_dtype, cov=True, gravity=0.0):
    """PyPose's IMUPreintegrator over a batch ``(B, F, 3)`` from the identity state."""
    import pypose as pp
    from _pypose_fix import fix_pypose_cumops

    fix_pypose_cumops()  # PyPose 0.9.5's scan under torch ≥ 2.14 (benchmarks/_pypose_fix.py)
    import torch

    B = gyro.shape[0]
    integ = pp.module.IMUPreintegrator(
        gravity=gravity,
        prop_cov=cov,
        reset=True,
        gyro_cov=torch.tensor([[NOISE.gyroscope_noise_density**2] * 3], dtype=torch_dtype),
        acc_cov=torch.tensor([[NOISE.accelerometer_noise_density**2] * 3], dtype=torch_dtype),
    ).to(torch_dtype)
    g = torch.as_tensor(gyro, dtype=torch_dtype)
    a = torch.as_tensor(accel, dtype=torch_dtype)
    d = torch.as_tensor(
        np.ascontiguousarray(np.broadcast_to(dt, gyro.shape[:-1])[..., None]), dtype=torch_dtype
    )
    init = {
        "pos": torch.zeros(B, 1, 3, dtype=torch_dtype),
        "rot": pp.identity_SO3(B, 1, dtype=torch_dtype),
        "vel": torch.zeros(B, 1, 3, dtype=torch_dtype),
    }
    with torch.no_grad():
        out = integ(d, g, a, init_state=init)
    return out["pos"][:, -1].numpy(), (out["cov"].numpy() if cov else None)


def have(module):
    try:
        __import__(module)
        return True
    except ImportError:
        return False


def rows_preintegration(quick, rows):
    n_long, n_win, w_len = (20_000, 512, 200) if quick else (100_000, 4096, 200)
    long, windows, bias = make_inputs(n_long, n_win, w_len)
    for name, data in (("preint-long", long), ("preint-windows", windows)):
        n = int(np.prod(data[0].shape[:-1]))
        ref = None
        for dtype in (jnp.float32, jnp.float64):
            g, a, d = (jnp.asarray(x, dtype) for x in data)
            b = jaximu.ImuBias(jnp.asarray(bias[0], dtype), jnp.asarray(bias[1], dtype))
            method = "parallel" if name == "preint-long" else "sequential"
            fn = jax.jit(lambda g, a, d: jaximu.preintegrate(g, a, d, b, NOISE, "euler", method))
            run, comp, mem, out = measure(lambda: block(fn(g, a, d)))
            if dtype == jnp.float64:
                ref = np.asarray(out.delta_p).reshape(-1, 3)
            rows.append(
                dict(
                    workload=name,
                    tool="jaximu",
                    dtype=jnp.dtype(dtype).name,
                    samples=n,
                    run_s=run,
                    compile_s=comp,
                    peak_mb=mem,
                )
            )
        # Peers get the bias-corrected samples where they have no bias input.
        gc = data[0] - bias[0]
        ac = data[1] - bias[1]
        if have("gtsam"):
            with PeakRss() as mem:
                pims, secs = gtsam_preintegrate(data, bias)
            pims = pims if isinstance(pims, list) else [pims]
            dp = np.array([p.deltaPij() for p in pims])
            rows.append(
                dict(
                    workload=name,
                    tool="gtsam",
                    dtype="float64",
                    samples=n,
                    run_s=secs,
                    compile_s=0.0,
                    peak_mb=mem.mb,
                    agreement=float(np.abs(dp - ref[-len(dp) :]).max()),
                )
            )
        else:
            rows.append(dict(workload=name, tool="gtsam", skipped="gtsam not installed"))
        if have("pypose"):
            import torch

            for tdt, nm in ((torch.float32, "float32"), (torch.float64, "float64")):
                gw, aw = (x.reshape((-1,) + x.shape[-2:]) for x in (gc, ac))
                run, comp, mem, out = measure(lambda: pypose_run(gw, aw, DT, tdt), reps=1)
                rows.append(
                    dict(
                        workload=name,
                        tool="pypose",
                        dtype=nm,
                        samples=n,
                        run_s=run,
                        compile_s=comp,
                        peak_mb=mem,
                        agreement=float(np.abs(out[0] - ref).max()),
                    )
                )
        else:
            rows.append(dict(workload=name, tool="pypose", skipped="pypose (torch) not installed"))
        # NumPy: the long sequence is a per-sample Python loop; cap it (rate is per sample).
        cap = 20_000 if name == "preint-long" else None
        gn, an = (x[..., :cap, :] if cap else x for x in (gc, ac))
        dn = (
            np.broadcast_to(data[2], data[0].shape[:-1])[..., :cap]
            if cap
            else np.broadcast_to(data[2], data[0].shape[:-1])
        )
        run, comp, mem, out = measure(lambda: numpy_preintegrate(gn, an, dn), reps=1)
        m = int(np.prod(gn.shape[:-1]))
        row = dict(
            workload=name,
            tool="numpy",
            dtype="float64",
            samples=m,
            run_s=run,
            compile_s=0.0,
            peak_mb=mem,
        )
        if not cap:
            row["agreement"] = float(np.abs(out[1].reshape(-1, 3) - ref).max())
        rows.append(row)


def rows_propagation(quick, rows):
    g_w = np.array([0.0, 0.0, -9.81])
    for name, (B, T), cov in (
        ("mean", (2048, 200) if quick else (16384, 200), False),
        ("cov", (256, 500) if quick else (1024, 1000), True),
    ):
        rng = np.random.default_rng(0)
        gyro = rng.normal(0, 0.5, (B, T, 3))
        accel = np.array([0, 0, 9.81]) + rng.normal(0, 0.5, (B, T, 3))
        dt = np.full(T, DT)
        ref = None
        for dtype in (jnp.float32, jnp.float64):
            g, a, d = (jnp.asarray(x, dtype) for x in (gyro, accel, dt))
            x0 = jaximu.NavState.identity((B,), dtype)
            if cov:
                P0 = jnp.eye(15, dtype=dtype) * 1e-6
                fn = jax.jit(
                    lambda g, a, d: jaximu.propagate_covariance_final(
                        x0, P0, g, a, d, NOISE, "euler"
                    )
                )
            else:
                fn = jax.jit(lambda g, a, d: jaximu.propagate_final(x0, g, a, d, "euler"))
            run, comp, mem, out = measure(lambda: block(fn(g, a, d)))
            if dtype == jnp.float64:
                ref = np.asarray(out[0].p if cov else out.p)
            rows.append(
                dict(
                    workload=name,
                    tool="jaximu",
                    dtype=jnp.dtype(dtype).name,
                    samples=B * T,
                    run_s=run,
                    compile_s=comp,
                    peak_mb=mem,
                )
            )
        if have("pypose"):
            import torch

            for tdt, nm in ((torch.float32, "float32"), (torch.float64, "float64")):
                run, comp, mem, out = measure(
                    lambda: pypose_run(gyro, accel, dt, tdt, cov=cov, gravity=9.81), reps=1
                )
                rows.append(
                    dict(
                        workload=name,
                        tool="pypose",
                        dtype=nm,
                        samples=B * T,
                        run_s=run,
                        compile_s=comp,
                        peak_mb=mem,
                        agreement=float(np.abs(out[0] - ref).max()),
                    )
                )
        else:
            rows.append(dict(workload=name, tool="pypose", skipped="pypose (torch) not installed"))
        run, comp, mem, out = measure(lambda: numpy_propagate(gyro, accel, dt, g_w, cov), reps=1)
        rows.append(
            dict(
                workload=name,
                tool="numpy",
                dtype="float64",
                samples=B * T,
                run_s=run,
                compile_s=0.0,
                peak_mb=mem,
                agreement=float(np.abs(out[1] - ref).max()),
            )
        )


def rows_montecarlo(quick, rows):
    from montecarlo import T as MC_T
    from montecarlo import bench_gtsam as mc_gtsam
    from montecarlo import bench_jaximu as mc_jaximu

    n_runs = 2000 if quick else 10_000
    for dtype in (jnp.float32, jnp.float64):
        with PeakRss() as mem:
            secs, comp, _ = mc_jaximu(n_runs, dtype)
        rows.append(
            dict(
                workload="montecarlo",
                tool="jaximu",
                dtype=jnp.dtype(dtype).name,
                samples=n_runs * MC_T,
                run_s=secs,
                compile_s=comp,
                peak_mb=mem.mb,
            )
        )
    if have("gtsam"):
        with PeakRss() as mem:
            secs, _ = mc_gtsam(n_runs)
        rows.append(
            dict(
                workload="montecarlo",
                tool="gtsam",
                dtype="float64",
                samples=n_runs * MC_T,
                run_s=secs,
                compile_s=0.0,
                peak_mb=mem.mb,
            )
        )
    else:
        rows.append(dict(workload="montecarlo", tool="gtsam", skipped="gtsam not installed"))


# --------------------------------------------------------------------------- reporting


def ratios(rows):
    """``{"<workload> <dtype> jaximu/<peer>": ratio}``: jaximu's samples/s in ``dtype`` over
    the peer's in the same dtype, or over its float64 row where it has only that."""
    out = {}
    done = [r for r in rows if not r.get("skipped")]
    for r in done:
        if r["tool"] == "jaximu":
            continue
        peer_dtypes = {
            p["dtype"] for p in done if p["tool"] == r["tool"] and p["workload"] == r["workload"]
        }
        for d in ("float32", "float64"):
            if r["dtype"] != (d if d in peer_dtypes else "float64"):
                continue
            j = [
                x
                for x in done
                if x["tool"] == "jaximu" and x["workload"] == r["workload"] and x["dtype"] == d
            ]
            if j:
                out[f"{r['workload']} {d} jaximu/{r['tool']}"] = (
                    j[0]["samples"] / j[0]["run_s"]
                ) / (r["samples"] / r["run_s"])
    return out


def table(rows, rats):
    lines = [
        "| workload | tool | dtype | samples/s | run s | compile s | peak MB | "
        "agreement [m] | jaximu f32 × | jaximu f64 × |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r.get("skipped"):
            lines.append(
                f"| {r['workload']} | {r['tool']} | - | skipped: {r['skipped']} | | | | | | |"
            )
            continue
        rate = r["samples"] / r["run_s"]
        cells = []
        for d in ("float32", "float64"):
            rat = rats.get(f"{r['workload']} {d} jaximu/{r['tool']}")
            peer_has_d = any(
                p["tool"] == r["tool"] and p["workload"] == r["workload"] and p.get("dtype") == d
                for p in rows
            )
            show = rat is not None and (r["dtype"] == d or not peer_has_d)
            cells.append(f"{rat:.1f}" if show else "-")
        agree = f"{r['agreement']:.1e}" if "agreement" in r else "-"
        lines.append(
            f"| {r['workload']} | {r['tool']} | {r['dtype']} | {rate / 1e6:.3g} M | "
            f"{r['run_s']:.3f} | {r['compile_s']:.1f} | {r['peak_mb']:.0f} | {agree} | "
            f"{cells[0]} | {cells[1]} |"
        )
    return "\n".join(lines)


def read_baseline(path):
    """The ratios of an earlier run's JSON (read before this run writes its own, which may be
    the same file)."""
    with open(path) as f:
        return json.load(f)["ratios"]


def check(rats, base):
    worse = []
    for key, old in base.items():
        new = rats.get(key)
        if new is None:
            print(f"  {key}: not measured in this run (baseline {old:.2f})")
        elif new < (1 - TOLERANCE) * old:
            worse.append(key)
            print(
                f"  REGRESSION {key}: {new:.2f} against {old:.2f} (-{100 * (1 - new / old):.0f}%)"
            )
        else:
            print(f"  ok {key}: {new:.2f} (baseline {old:.2f})")
    return worse


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes")
    ap.add_argument("--only", choices=("preint", "propagation", "montecarlo"), default=None)
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/)")
    ap.add_argument(
        "--check",
        default=None,
        metavar="BASELINE",
        help="exit 1 if a ratio is more than 30%% worse than in BASELINE",
    )
    args = ap.parse_args(argv)
    baseline = read_baseline(args.check) if args.check else None
    info = machine_info()
    print(
        f"# peers on {info['cpu_model']} ({info['cpus_usable']} usable CPUs), jax "
        f"{jax.__version__}, backend {jax.default_backend()}",
        flush=True,
    )
    rows = []
    if args.only in (None, "preint"):
        rows_preintegration(args.quick, rows)
    if args.only in (None, "propagation"):
        rows_propagation(args.quick, rows)
    if args.only in (None, "montecarlo"):
        rows_montecarlo(args.quick, rows)
    rats = ratios(rows)
    md = table(rows, rats)
    print(md)
    slug = machine_slug(info) + ("-quick" if args.quick else "")
    base = os.path.join(os.path.dirname(__file__), "results")
    out = args.out or os.path.join(base, f"peers-{slug}.json")
    with open(out, "w") as f:
        json.dump(dict(machine=info, quick=args.quick, rows=rows, ratios=rats), f, indent=1)
    with open(os.path.splitext(out)[0] + ".md", "w") as f:
        f.write(
            f"Measured on {info['cpu_model']} ({info['cpus_usable']} usable CPUs), "
            f"jax {info['jax']}.\n\n{md}\n"
        )
    print(f"wrote {out} and its .md")
    if args.check:
        print(f"regression check against {args.check} (ratios, tolerance {TOLERANCE:.0%}):")
        if check(rats, baseline):
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
