"""C++/Eigen reference row for the preintegration benchmark.

    python benchmarks/cpp_reference.py           # both workloads, ~1 min on a 2-core CPU
    python benchmarks/cpp_reference.py --quick   # small sizes

:func:`run_cpp_reference` compiles ``benchmarks/cpp/preintegrate_reference.cpp`` (our own
Eigen program: Euler / Forster preintegration with the 9×9 covariance of ``[δθ, δp, δv]``
and the five bias Jacobians, double precision, one core) with
``g++ -O3 -march=native -std=c++17 -DNDEBUG`` into ``benchmarks/results/.build/`` (cached by
a hash of the source, the flags and the compiler version), runs it on the given samples
and returns its timings and results. Without a compiler or Eigen it prints why and returns
``None``; it never raises.

Basalt itself (the C++ peer of the targets) is timed on the same samples when its headers are
given: ``BASALT_HEADERS_DIR`` set to a checkout of basalt-headers with its submodules
(``git clone --recursive https://gitlab.com/VladyslavUsenko/basalt-headers``; it needs
``include/basalt`` and ``thirdparty/Sophus``, or Sophus in ``SOPHUS_INCLUDE_DIR``). The
program is then built with ``-DJAXIMU_WITH_BASALT`` and has a third kernel, ``"basalt"``:
``basalt::IntegratedImuMeasurement<double>::integrate`` sample by sample. Without them that
kernel is skipped with the reason printed.

Run as a script it times both workloads of ``benchmarks/preintegration.py`` (the same
samples, from its ``make_inputs``), runs ``jaximu.preintegrate(..., scheme="euler")`` in
float64 on them, and prints the C++ speed and the agreement of every output with jaximu.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
SOURCE = os.path.join(HERE, "cpp", "preintegrate_reference.cpp")
BUILD_DIR = os.path.join(HERE, "results", ".build")
FLAGS = ("-O3", "-march=native", "-std=c++17", "-DNDEBUG")
KERNELS = ("blocked", "dense")
OUT_SIZE = 137  # doubles per window in the program's dump
FIELDS = (  # name, shape, offset in a dumped window
    ("delta_t", (), 0),
    ("delta_q", (4,), 1),
    ("delta_v", (3,), 5),
    ("delta_p", (3,), 8),
    ("cov", (9, 9), 11),
    ("dR_dbg", (3, 3), 92),
    ("dp_dbg", (3, 3), 101),
    ("dp_dba", (3, 3), 110),
    ("dv_dbg", (3, 3), 119),
    ("dv_dba", (3, 3), 128),
)
JACOBIANS = ("dR_dbg", "dp_dbg", "dp_dba", "dv_dbg", "dv_dba")


def _say(msg, verbose=True):
    if verbose:
        print(f"C++ reference: {msg}", file=sys.stderr, flush=True)


def find_toolchain():
    """``(compiler, eigen_include_dir, None)``, or ``(None, None, reason)``.

    The compiler is ``$CXX`` if set, else ``g++``; Eigen is looked for in
    ``$EIGEN3_INCLUDE_DIR``, ``pkg-config eigen3`` and the usual prefixes.
    """
    cxx = shutil.which(os.environ.get("CXX") or "g++")
    if cxx is None:
        return None, None, f"no C++ compiler ({os.environ.get('CXX') or 'g++'} not on PATH)"
    candidates = [os.environ.get("EIGEN3_INCLUDE_DIR")]
    if shutil.which("pkg-config"):
        try:
            flags = subprocess.run(
                ["pkg-config", "--cflags-only-I", "eigen3"],
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout.split()
            candidates += [f[2:] for f in flags if f.startswith("-I")]
        except (OSError, subprocess.SubprocessError):
            pass
    prefixes = [os.environ.get("CONDA_PREFIX"), sys.prefix, "/usr/local", "/usr", "/opt/homebrew"]
    candidates += [os.path.join(p, "include", "eigen3") for p in prefixes if p]
    for inc in candidates:
        if inc and os.path.isfile(os.path.join(inc, "Eigen", "Core")):
            return cxx, inc, None
    return None, None, "Eigen not found (apt-get install libeigen3-dev, or set EIGEN3_INCLUDE_DIR)"


def find_basalt():
    """``(include flags, None)`` for Basalt's headers and Sophus, or ``(None, reason)``.

    ``BASALT_HEADERS_DIR``: a basalt-headers checkout with ``include/basalt`` and, unless
    ``SOPHUS_INCLUDE_DIR`` names Sophus elsewhere, its submodule ``thirdparty/Sophus``."""
    root = os.environ.get("BASALT_HEADERS_DIR")
    if not root:
        return None, "BASALT_HEADERS_DIR is not set (a basalt-headers checkout, see above)"
    inc = os.path.join(root, "include")
    if not os.path.isfile(os.path.join(inc, "basalt", "imu", "preintegration.h")):
        return None, f"no include/basalt/imu/preintegration.h under BASALT_HEADERS_DIR={root}"
    sophus = os.environ.get("SOPHUS_INCLUDE_DIR") or os.path.join(root, "thirdparty", "Sophus")
    if not os.path.isfile(os.path.join(sophus, "sophus", "so3.hpp")):
        return None, (
            f"Sophus not found in {sophus} (clone basalt-headers with --recursive, "
            "or set SOPHUS_INCLUDE_DIR)"
        )
    return ("-DJAXIMU_WITH_BASALT", f"-I{inc}", f"-I{sophus}"), None


def build(verbose=True):
    """``(path of the compiled program, compiler command, with_basalt)`` (compiled on first
    use), or ``None`` with a printed reason. ``with_basalt``: the program has the
    ``"basalt"`` kernel (:func:`find_basalt`)."""
    cxx, inc, reason = find_toolchain()
    if cxx is None:
        _say(f"skipped: {reason}", verbose)
        return None
    command = " ".join([os.path.basename(cxx), *FLAGS])
    basalt, _ = find_basalt()
    extra = basalt or ()
    try:
        version = subprocess.run(
            [cxx, "--version"], capture_output=True, text=True, timeout=30
        ).stdout
        with open(SOURCE, "rb") as f:
            src = f.read()
        key = hashlib.sha256(
            src + "\0".join((cxx, version, inc) + FLAGS + extra).encode()
        ).hexdigest()
        exe = os.path.join(BUILD_DIR, f"preintegrate_reference-{key[:16]}")
        if os.path.isfile(exe) and os.access(exe, os.X_OK):
            return exe, command, basalt is not None
        os.makedirs(BUILD_DIR, exist_ok=True)
        tmp = f"{exe}.{os.getpid()}.tmp"
        cmd = [cxx, *FLAGS, *extra, f"-I{inc}", SOURCE, "-o", tmp]
        _say("compiling: " + " ".join(cmd), verbose)
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        if proc.returncode != 0:
            err = "\n".join(proc.stderr.strip().splitlines()[-15:])
            _say(f"skipped: compilation failed ({proc.returncode}):\n{err}", verbose)
            return None
        os.replace(tmp, exe)
        return exe, command, basalt is not None
    except (OSError, subprocess.SubprocessError) as e:
        _say(f"skipped: build failed: {e}", verbose)
        return None


def _noise_densities(noise):
    """``(σ_g[3], σ_a[3])`` from an :class:`jaximu.ImuNoise` or a ``(σ_g, σ_a)`` pair."""
    if hasattr(noise, "gyroscope_noise_density"):
        sg, sa = noise.gyroscope_noise_density, noise.accelerometer_noise_density
    else:
        sg, sa = noise
    return (
        np.broadcast_to(np.asarray(sg, np.float64), (3,)),
        np.broadcast_to(np.asarray(sa, np.float64), (3,)),
    )


def write_input(path, gyro, accel, dt, b_g, b_a, noise):
    """The program's input file; returns ``(N, L)``. ``gyro``: ``(L, 3)`` or ``(N, L, 3)``."""
    gyro = np.asarray(gyro, np.float64)
    accel = np.asarray(accel, np.float64)
    if gyro.ndim not in (2, 3) or gyro.shape[-1] != 3 or accel.shape != gyro.shape:
        raise ValueError(
            f"gyro and accel must both be (L, 3) or (N, L, 3), got {gyro.shape} and {accel.shape}"
        )
    g3 = gyro.reshape((-1,) + gyro.shape[-2:])
    N, L = g3.shape[:2]
    rows = np.empty((N, L, 7), np.float64)
    rows[..., 0:3] = g3
    rows[..., 3:6] = accel.reshape(g3.shape)
    rows[..., 6] = np.broadcast_to(np.asarray(dt, np.float64), gyro.shape[:-1]).reshape(N, L)
    sg, sa = _noise_densities(noise)
    header = np.concatenate(
        [np.asarray(b_g, np.float64).reshape(3), np.asarray(b_a, np.float64).reshape(3), sg, sa]
    )
    with open(path, "wb") as f:
        f.write(b"JXPI0001")
        f.write(np.array([N, L], "<i8").tobytes())
        f.write(header.astype("<f8").tobytes())
        f.write(rows.astype("<f8").tobytes())
    return N, L


def _unpack(flat, batched):
    out = {}
    for name, shape, off in FIELDS:
        n = int(np.prod(shape, dtype=int))
        x = flat[:, off : off + n].reshape((flat.shape[0],) + shape)
        out[name] = x if batched else x[0]
    return out


def run_cpp_reference(
    gyro, accel, dt, b_g, b_a, noise, workload=None, *, kernels=KERNELS, min_time=0.3, verbose=True
):
    """Run the C++/Eigen reference on the samples; ``None`` (reason printed) if unavailable.

    Args:
        gyro, accel: ``(L, 3)`` (one window) or ``(N, L, 3)`` (N windows) raw samples.
        dt: scalar, ``(L,)`` or ``(N, L)`` steps [s].
        b_g, b_a: ``(3,)`` linearisation bias (shared by the windows).
        noise: :class:`jaximu.ImuNoise` or ``(σ_g, σ_a)`` densities (scalars or per axis).
        workload: a label for messages (e.g. ``"long"``, ``"windows"``).
        kernels: which covariance kernels to time: ``"blocked"`` (block-structured 3×3
            updates), ``"dense"`` (9×9 ``F P Fᵀ + G Q Gᵀ``) and/or ``"basalt"`` (Basalt's
            own class, when its headers are found: :func:`find_basalt`; otherwise left out,
            with the reason printed).
        min_time: each kernel is repeated (≥ 3 runs) until its runs add up to this [s].

    Returns:
        ``{"windows", "window_len", "samples", "compiler", "eigen", "command", "kernels"}``
        where ``kernels[name]`` has ``best_s``, ``total_s``, ``reps``, ``us_per_sample``,
        ``samples_per_s`` and ``result``: ``delta_t``, ``delta_q`` (w x y z), ``delta_v``,
        ``delta_p``, ``cov`` (9×9, ``[δθ, δp, δv]``) and the bias Jacobians ``dR_dbg``,
        ``dp_dbg``, ``dp_dba``, ``dv_dbg``, ``dv_dba`` as numpy arrays, with a leading
        ``(N,)`` axis for batched input.
    """
    label = f" ({workload})" if workload else ""
    try:
        built = build(verbose)
        if built is None:
            return None
        exe, command, with_basalt = built
        if "basalt" in kernels and not with_basalt:
            _say(f"Basalt skipped{label}: {find_basalt()[1]}", verbose)
            kernels = tuple(k for k in kernels if k != "basalt")
            if not kernels:
                return None
        with tempfile.TemporaryDirectory(prefix="jaximu-cpp-") as tmp:
            inp = os.path.join(tmp, "input.bin")
            N, L = write_input(inp, gyro, accel, dt, b_g, b_a, noise)
            dump = os.path.join(tmp, "out")
            cmd = [
                exe,
                inp,
                "--min-time",
                repr(float(min_time)),
                "--kernels",
                ",".join(kernels),
                "--dump",
                dump,
            ]
            _say(f"running{label}: {N} × {L} samples, kernels {','.join(kernels)}", verbose)
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
            if proc.returncode != 0:
                _say(
                    f"skipped{label}: the program failed ({proc.returncode}): "
                    f"{proc.stderr.strip()}",
                    verbose,
                )
                return None
            meta = json.loads(proc.stdout)
            batched = np.ndim(gyro) == 3
            for name, k in meta["kernels"].items():
                flat = np.fromfile(f"{dump}_{name}.bin", "<f8").reshape(N, OUT_SIZE)
                k["result"] = _unpack(flat, batched)
                k.pop("first", None)  # window 0 of the dump, printed for humans
        meta["command"] = command
        return meta
    except Exception as e:  # noqa: BLE001  (an optional row: report, never fail the benchmark)
        _say(f"skipped{label}: {type(e).__name__}: {e}", verbose)
        return None


def agreement(result, pim):
    """Max abs difference of every output of a C++ ``result`` from a jaximu ``Preintegrated``.

    Returns ``{field: (max abs diff, max abs value of jaximu's)}`` for ``delta_q`` (sign
    aligned), ``delta_v``, ``delta_p``, ``cov`` and the five bias Jacobians.
    """
    out = {}
    for name in ("delta_q", "delta_v", "delta_p", "cov") + JACOBIANS:
        ref = np.asarray(getattr(pim, name), np.float64)
        x = np.broadcast_to(result[name], ref.shape)
        if name == "delta_q":  # q and -q are the same rotation
            sign = np.where(np.sum(x * ref, axis=-1, keepdims=True) < 0, -1.0, 1.0)
            x = sign * x
        out[name] = (float(np.abs(x - ref).max()), float(np.abs(ref).max()))
    return out


def worst_relative(agree):
    """The largest ``diff / max|value|`` over the fields of :func:`agreement`."""
    return max(d / s if s > 0 else d for d, s in agree.values())


def main(argv=None):
    import argparse
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from preintegration import best_time, make_inputs  # same folder

    import jaximu

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--min-time", type=float, default=0.3, help="timing budget per kernel [s]")
    args = ap.parse_args(argv)
    n_long, n_win, w_len = (20_000, 512, 200) if args.quick else (100_000, 4096, 200)
    long, windows, bias = make_inputs(n_long, n_win, w_len)
    noise = jaximu.ImuNoise.euroc()
    lines = []
    for name, data in (("long", long), ("windows", windows)):
        ref = run_cpp_reference(*data, *bias, noise, name, min_time=args.min_time)
        if ref is None:
            return 1
        gyro, accel, dt = (jnp.asarray(x, jnp.float64) for x in data)
        b = jaximu.ImuBias(jnp.asarray(bias[0], jnp.float64), jnp.asarray(bias[1], jnp.float64))
        fn = jax.jit(lambda g, a, d: jaximu.preintegrate(g, a, d, b, noise, "euler", "sequential"))
        t0 = time.perf_counter()
        pim = jax.block_until_ready(fn(gyro, accel, dt))
        first = time.perf_counter() - t0
        jax_s = best_time(lambda: fn(gyro, accel, dt))
        n = ref["samples"]
        for kname, k in ref["kernels"].items():
            agree = agreement(k["result"], pim)
            lines.append((name, n, kname, k, agree, n / jax_s))
        print(
            f"{name}: jaximu f64 sequential {n / jax_s / 1e6:.3f} M samples/s "
            f"(first call {first:.1f} s)",
            file=sys.stderr,
            flush=True,
        )

    print(
        f"\n# C++ Eigen reference ({ref['command']}; {ref['compiler']}, Eigen {ref['eigen']}),"
        " one core, float64, best of ≥ 3 runs"
    )
    print(
        "\n| workload | kernel | µs/sample | samples/s | jaximu f64 seq / C++ | "
        "max abs diff vs jaximu f64: q / v / p / cov / bias Jacobians | worst relative |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, n, kname, k, agree, jrate in lines:
        jac = max(agree[j][0] for j in JACOBIANS)
        diffs = " / ".join(f"{agree[f][0]:.1e}" for f in ("delta_q", "delta_v", "delta_p", "cov"))
        print(
            f"| {name} ({n}) | {kname} | {k['us_per_sample']:.3f} | "
            f"{k['samples_per_s'] / 1e6:.3f} M | {jrate / k['samples_per_s']:.2f} | "
            f"{diffs} / {jac:.1e} | {worst_relative(agree):.1e} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
