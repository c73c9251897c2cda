"""The `jaximu` command end to end, in a subprocess, on the bundled real EuRoC excerpt.

The subprocesses keep their compilations in the suite's temporary folder (conftest.py sets
JAXIMU_CACHE_DIR), never in the user's ~/.cache."""

import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from jaximu.datasets import euroc_v1_02_segment

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"


def run(*args, cwd=None, default_codegen=False):
    """``python -m jaximu *args``; ``default_codegen``: with the caller's XLA flags only, not
    the suite's fast-compile ones (conftest.py), so XLA's default code generation runs."""
    env = None
    if default_codegen:
        env = dict(os.environ, XLA_FLAGS=os.environ.get("JAXIMU_TEST_CALLER_XLA_FLAGS", ""))
    return subprocess.run(
        [sys.executable, "-m", "jaximu", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
        env=env,
    )


def run_here(capsys, *args):
    """The command in this process (``jaximu.cli.main``, what ``python -m jaximu`` calls),
    with :func:`run`'s result fields: no interpreter and JAX start-up (~2.5 s a call)."""
    from jaximu import cli

    try:
        code = cli.main([str(a) for a in args])
    except SystemExit as e:  # argparse: --help, invalid choices
        code = e.code
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["jaximu", *args], code, out, err)


def test_bundled_segment_is_intact():
    """The excerpt keeps EuRoC's exact int64 nanosecond stamps and 200 Hz grid."""
    seg = euroc_v1_02_segment()
    assert seg.t0_ns == 1403715524907142912
    assert seg.gyro.shape == (4002, 3) and seg.q_gt.shape == (4001, 4)
    np.testing.assert_allclose(np.diff(seg.t), 0.005, atol=2e-6)
    assert abs(seg.t_gt[0] - 256e-9) < 1e-12  # GT stamp 256 ns after the first IMU stamp
    # Still at the start: the accelerometer reads ~g.
    assert abs(np.linalg.norm(seg.accel[:200].mean(axis=0)) - 9.81) < 0.05


def test_demo_runs_and_reports_drift(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "demo.png"
    res = run("demo", "--seconds", "2", "--plot", str(out), default_codegen=True)
    assert res.returncode == 0, res.stderr
    assert "EuRoC MAV V1_02_medium" in res.stdout and "position drift" in res.stdout
    lines = [
        ln for ln in res.stdout.splitlines() if ln.split()[:1] in (["euler"], ["midpoint"], ["rk4"])
    ]
    assert len(lines) == 3
    # Dead reckoning over 2 s from the ground-truth state: centimetres, not metres (a wrong
    # gravity sign or quaternion order gives tens of metres).
    drift_2s = float(lines[1].split()[-5])
    assert drift_2s < 0.3
    assert out.exists() and out.stat().st_size > 10_000


def test_demo_without_plot():
    # the length and XLA flags of test_demo_runs_and_reports_drift: its compilations, from
    # the suite's compilation cache (conftest.py: JAXIMU_CACHE_DIR), are reused
    res = run("demo", "--seconds", "2", "--no-plot", default_codegen=True)
    assert res.returncode == 0, res.stderr
    assert "plot written" not in res.stdout


def one_line_error(res, *fragments):
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1, res.stderr
    for f in fragments:
        assert f in errors[0], errors[0]


def test_user_mistakes_exit_non_zero_without_traceback(tmp_path, capsys):
    """As processes: one mistake caught by the argument parser, one by a reader (exit status
    and stderr of ``python -m jaximu`` itself); the others through the same ``cli.main`` in
    this process (each subprocess costs a JAX start-up)."""
    one_line_error(run("frobnicate"), "invalid choice")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,wx,wy,wz,ax,ay,az\n0.000,0,0,0,0,0,9.8\n0.005,0,0\n")
    one_line_error(run("propagate", str(bad)), "line 3", "expected at least 7 columns")
    here = lambda *a: run_here(capsys, *a)
    one_line_error(here("demo", "--seconds", "-1", "--no-plot"), "--seconds must be positive")
    one_line_error(here("propagate", str(tmp_path / "missing.csv")), "no such file", "missing.csv")
    one_line_error(here("calibrate", str(bad)), "line 3")
    one_line_error(here("propagate", str(DATA / "tumvi_room4"), "--bias", "1 2"), "--bias needs 6")
    one_line_error(
        here("propagate", str(DATA / "tumvi_room4"), "--duration", "0"),
        "--duration must be positive",
    )
    one_line_error(
        here("propagate", str(DATA / "tumvi_room4"), "--out", str(tmp_path / "no" / "x.tum")),
        "does not exist",
    )
    in_g = tmp_path / "g.csv"  # an accelerometer in g: the advice names the command's flag
    in_g.write_text("".join(f"{0.005 * k:.3f},0,0,0,0,0,1.0\n" for k in range(50)))
    one_line_error(here("propagate", str(in_g)), "in g? pass --accel-unit g")


def test_help_of_every_command(capsys):
    """The top-level help as a process; each command's help from the same parser in this
    process (argparse prints it and exits 0)."""
    res = run("--help")
    assert res.returncode == 0
    for cmd in ("demo", "propagate", "preintegrate", "montecarlo", "calibrate", "allan"):
        assert cmd in res.stdout
        sub = run_here(capsys, cmd, "--help")
        assert sub.returncode == 0 and f"usage: jaximu {cmd}" in sub.stdout, sub.stderr


def test_propagate_euroc_segment_from_ground_truth(tmp_path):
    from jaximu import io

    pytest.importorskip("matplotlib")
    tum, states, png = tmp_path / "traj.tum", tmp_path / "states.npz", tmp_path / "p.png"
    res = run(
        "propagate",
        str(DATA / "euroc_v1_02_medium"),
        "--init-from-groundtruth",
        "--out",
        str(tum),
        "--states",
        str(states),
        "--plot",
        str(png),
    )
    assert res.returncode == 0, res.stderr
    assert "initial state from the ground truth (pose, velocity, biases)" in res.stdout
    data = io.read_euroc(DATA / "euroc_v1_02_medium")
    stamps, p, q = io.read_tum(tum)
    np.testing.assert_array_equal(stamps, data.stamps_ns)  # one pose per IMU sample, exact
    # the first pose is the ground truth's at the first sample
    np.testing.assert_allclose(p[0], data.ground_truth.p[0], atol=2e-3)
    # dead reckoning over 1 s from the truth: centimetres (tens of metres if a convention broke)
    row = next(ln for ln in res.stdout.splitlines() if ln.split()[:1] == ["1"])
    assert float(row.split()[1]) < 0.2
    s_stamps, s_states, cov = io.read_states(states)
    np.testing.assert_array_equal(s_stamps, data.stamps_ns)
    np.testing.assert_allclose(s_states.p, p, atol=1e-6)
    assert cov.shape == (len(data), 15, 15) and np.all(np.diagonal(cov, axis1=1, axis2=2) > 0)
    assert png.stat().st_size > 20_000


def test_propagate_without_ground_truth_init_says_how(tmp_path):
    res = run(
        "propagate",
        str(DATA / "tumvi_room4"),
        "--duration",
        "1",
        "--noise",
        "tum-vi",
        "--out",
        str(tmp_path / "t.tum"),
    )
    assert res.returncode == 0, res.stderr
    assert "gravity alignment" in res.stdout and "biases zero" in res.stdout
    assert "not initialised from it" in res.stdout  # TUM-VI has mocap: compared, with a warning
    assert len((tmp_path / "t.tum").read_text().splitlines()) > 150


def test_chunked_propagation_equals_one_call():
    """The command propagates chunk by chunk (progress bar): the same numbers as one call."""
    import jax.numpy as jnp

    import jaximu
    from jaximu import cli, io

    data = io.read_euroc(DATA / "euroc_v1_02_medium").select(slice(0, 700))
    state0, _ = io.initial_state(data, still_seconds=1.0)
    P0 = np.diag(np.full(15, 1e-4))
    noise = jaximu.ImuNoise.euroc()
    t, states, cov = cli.propagate_recording(
        data, state0, P0, noise, "midpoint", jnp.float64, chunk=233
    )
    ref_states, ref_cov = jaximu.propagate_covariance(
        state0, P0, data.gyro, data.accel, data.dt, noise, "midpoint"
    )
    assert len(t) == len(states.p) == 700
    np.testing.assert_allclose(states.p[1:], ref_states.p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(states.q[1:], ref_states.q, rtol=0, atol=1e-14)
    np.testing.assert_allclose(cov[1:], ref_cov, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(cov[0], P0)
