"""A whole recording through the propagator: state and covariance chunk by chunk (what
``jaximu propagate`` runs), and the dead-reckoning demo on the bundled EuRoC excerpt (what
``jaximu demo`` runs).

* :func:`propagate_recording`: an :class:`jaximu.io.ImuData` from its first sample to its
  last, the mean and the 15×15 covariance, exactly as one :func:`jaximu.propagate_covariance`
  call (consecutive chunks share their boundary sample).
* :func:`run_demo`: every scheme on ``jaximu/data/euroc_v1_02_medium`` against its ground
  truth; the drift table.
* :func:`noise_preset`, :func:`default_P0`: the noise densities and initial uncertainty the
  command uses.

JAX is imported when a function runs, not with the module (``jaximu --help`` stays quick).
"""

from __future__ import annotations

import contextlib
import pathlib
import sys
import time

import numpy as np

from jaximu import io
from jaximu.engine.errorstate import _check_cov, propagate_covariance
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.sensor import check_pose
from jaximu.geometry.state import check_state
from jaximu.schemes.integrators import SCHEMES
from jaximu.schemes.world import check_omega
from jaximu.studies.plots import plot_trajectory

__all__ = [
    "DEMO_SCHEMES",
    "DEMO_SECONDS",
    "NOISE_PRESETS",
    "default_P0",
    "noise_preset",
    "propagate_recording",
    "run_demo",
]

#: The schemes the demo runs (and the command offers).
DEMO_SCHEMES = ("euler", "midpoint", "rk4")
#: Seconds of ground truth in the bundled excerpt (the demo's longest run).
DEMO_SECONDS = 20.0
#: The names :func:`noise_preset` takes.
NOISE_PRESETS = ("euroc", "tum-vi")
_DEMO_REPORT_AT = (1, 2, 5, 10, 20, 30, 60)


def noise_preset(name: str):
    """The :class:`jaximu.ImuNoise` of a dataset's IMU: ``"euroc"`` (ADIS16448, as EuRoC's
    Kalibr file) or ``"tum-vi"`` (BMI160, as TUM-VI's)."""
    val.check_choice("noise", name, NOISE_PRESETS, "noise preset")
    return {"euroc": ImuNoise.euroc, "tum-vi": ImuNoise.tum_vi}[name]()


def default_P0(from_groundtruth: bool) -> np.ndarray:
    """Initial uncertainty ``(15, 15)`` of ``[dθ, dp, dv, db_g, db_a]``: the ground truth's own
    (~0.1°, 1 mm, 1 cm/s) when starting from it, else a gravity alignment's (1° tilt, 10°
    yaw, position/velocity known: the origin and still); the biases' turn-on spread of a
    MEMS IMU (1e-3 rad/s, 3e-2 m/s²) either way."""
    att = [np.deg2rad(0.1)] * 3 if from_groundtruth else [np.deg2rad(1.0)] * 2 + [np.deg2rad(10.0)]
    sig = np.r_[att, [1e-3] * 3, [1e-2] * 3, [1e-3] * 3, [3e-2] * 3]
    return np.diag(sig**2)


def _progress(total, desc, enabled, unit="sample"):
    """A tqdm bar on stderr (``pip install "jaximu[progress]"``), or None."""
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    # disable=None: no bar when stderr is not a terminal (logs, CI, subprocess pipes)
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        unit_scale=True,
        file=sys.stderr,
        leave=False,
        disable=None,
    )


def save_plot(make, path, out=None) -> None:
    """Write the figure ``make()`` returns to ``path`` (nothing when ``path`` is empty) and
    say so on ``out`` (default ``sys.stdout``); without matplotlib, say that instead."""
    if not path:
        return
    out = out if out is not None else sys.stdout
    try:
        import matplotlib

        matplotlib.use("Agg")
    except ImportError:
        print('matplotlib is not installed: no plot (pip install "jaximu[examples]")', file=out)
        return
    import matplotlib.pyplot as plt

    fig = make()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"plot written to {path}", file=out)


def propagate_recording(
    data,
    state0,
    P0,
    noise,
    scheme,
    dtype,
    *,
    gravity=9.81,
    chunk=2000,
    progress=False,
    body_P_sensor=None,
    omega_coriolis=None,
):
    """Propagate state and covariance through a whole recording, chunk by chunk (for the
    progress bar), exactly as one call: consecutive chunks share their boundary sample, and
    the intervals ``dt`` are the ends-of-interval form of :func:`jaximu.propagate`.

    Args:
        data: a :class:`jaximu.io.ImuData` (validated by its reader).
        state0: the :class:`jaximu.NavState` at ``data.t[0]`` (unbatched).
        P0: ``(15, 15)`` symmetric PSD covariance of ``[dθ, dp, dv, db_g, db_a]``.
        noise: :class:`jaximu.ImuNoise` (continuous densities).
        scheme: ``"euler"``, ``"midpoint"`` or ``"rk4"``.
        dtype: the computation dtype, float32 or float64 (float64 needs ``jax_enable_x64``).
        gravity: magnitude ``g ≥ 0`` [m/s²] (``g_W = [0, 0, -g]``) or a ``(3,)`` vector.
        chunk: samples per compiled call (a positive integer).
        progress: show a progress bar on stderr (when it is a terminal and tqdm is there).
        body_P_sensor, omega_coriolis: as :func:`jaximu.propagate_covariance` (with a sensor
            pose, ``α`` at a chunk boundary is a one-sided difference: a first-order error at
            one sample in ``chunk``).

    All of these are checked before the work (the propagation runs under ``jit``, where
    the library's value checks cannot run).

    Returns:
        ``(t, states, cov)`` with numpy float64 arrays, the initial state included
        (``len(data)`` entries).

    Raises:
        ValueError: a bad argument (named), or a propagation that overflowed.
    """
    import jax
    import jax.numpy as jnp

    # the checks the jit below skips (traced values): run them on the concrete inputs first
    dtype = val.compute_dtype("dtype", dtype)
    val.check_choice("scheme", scheme, SCHEMES)
    chunk = val.check_int("chunk", chunk, 1)
    val.gravity_vector(gravity, dtype)
    noise = check_noise(noise, dtype)
    _check_cov(P0, dtype)
    check_state(jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), state0), dtype)
    if body_P_sensor is not None:
        check_pose(body_P_sensor, dtype)
    if omega_coriolis is not None:
        check_omega(omega_coriolis, dtype)
    step = jax.jit(
        lambda x, P, w, a, h: propagate_covariance(
            x,
            P,
            w,
            a,
            h,
            noise,
            scheme,
            gravity=gravity,
            body_P_sensor=body_P_sensor,
            omega_coriolis=omega_coriolis,
        )
    )
    gyro = jnp.asarray(data.gyro, dtype)
    accel = jnp.asarray(data.accel, dtype)
    dt = jnp.asarray(data.dt, dtype)
    x = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), state0)
    P = jnp.asarray(P0, dtype)
    n = len(data.dt)
    parts_x, parts_P = [x], [P[None]]
    bar = _progress(n, f"propagate ({scheme})", progress)
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        states, covs = step(x, P, gyro[lo : hi + 1], accel[lo : hi + 1], dt[lo:hi])
        x = jax.tree_util.tree_map(lambda a: a[-1], states)
        P = covs[-1]
        parts_x.append(states)
        parts_P.append(covs)
        if bar is not None:
            bar.update(hi - lo)
    if bar is not None:
        bar.close()
    parts_x[0] = jax.tree_util.tree_map(lambda a: a[None], parts_x[0])
    states = jax.tree_util.tree_map(
        lambda *a: np.concatenate([np.asarray(b, np.float64) for b in a]), *parts_x
    )
    cov = np.concatenate([np.asarray(c, np.float64) for c in parts_P])
    if not (
        np.isfinite(cov).all()
        and all(np.isfinite(np.asarray(f)).all() for f in jax.tree_util.tree_leaves(states))
    ):
        raise ValueError(
            "propagation produced non-finite values (overflow): check the units "
            "and the time stamps of the recording"
        )
    return data.t, states, cov


def run_demo(
    seconds: float = DEMO_SECONDS,
    scheme: str = "midpoint",
    plot: str | None = "jaximu_demo.png",
    out=None,
    progress: bool = False,
) -> dict:
    """Dead reckoning on the bundled EuRoC excerpt (V1_02_medium, 200 Hz) with every scheme,
    from the ground-truth state and biases, against the ground truth.

    Args:
        seconds: how long, ``0 < seconds ≤ DEMO_SECONDS`` (20 s of ground truth).
        scheme: the scheme the summary line and the plot show (one of ``DEMO_SCHEMES``).
        plot: a ``.png``/``.pdf``/``.svg`` file to write the plot to, or None.
        out: a text stream for the report (default ``sys.stdout``).
        progress: progress bars on stderr.

    Returns:
        The drift table ``{scheme: {t: (pos_m, vel_mps, att_deg)}}`` at 1, 2, 5, 10, 20 s
        (those within ``seconds``; else at ``seconds``).
    """
    from importlib import resources

    import jax
    import jax.numpy as jnp

    out = out if out is not None else sys.stdout
    seconds = val.check_positive("seconds", seconds)
    if seconds > DEMO_SECONDS:
        raise InputError(
            f"seconds={seconds:g}: the bundled excerpt holds {DEMO_SECONDS:g} s of ground truth",
            [Fix("seconds", DEMO_SECONDS)],
        )
    val.check_choice("scheme", scheme, DEMO_SCHEMES)
    if plot:  # checked before the work, not after it
        target = pathlib.Path(plot)
        if target.is_dir() or not target.parent.is_dir():
            raise ValueError(
                f"plot={str(plot)!r}: "
                + (
                    "is a folder; name a file in it"
                    if target.is_dir()
                    else f"the folder {target.parent} does not exist"
                )
            )
    with resources.as_file(resources.files("jaximu") / "data" / "euroc_v1_02_medium") as folder:
        data = io.read_euroc(folder)
    gt = data.ground_truth
    start = max(float(data.t[0]), gt.t[0] - io.CLOCK_TOLERANCE)  # where the truth starts
    data = data.window(start, seconds + io.CLOCK_TOLERANCE)
    dtype = jnp.result_type(float)  # float32 unless the user enabled x64
    state0, _ = io.initial_state(data, from_groundtruth=True)
    noise = noise_preset("euroc")
    P0 = default_P0(True)
    print(
        f"jaximu demo: EuRoC MAV V1_02_medium, {len(data.dt)} samples over "
        f"{data.duration:.2f} s at 200 Hz ({jnp.dtype(dtype).name}, {jax.default_backend()})",
        file=out,
    )
    print(
        "propagating from the ground-truth state with the ground-truth biases; "
        "no corrections (pure dead reckoning)",
        file=out,
    )
    report_at: list[float] = [s for s in _DEMO_REPORT_AT if s <= data.duration + 1e-9]
    if not report_at:  # shorter than the first mark: report at the end
        report_at = [round(float(seconds), 3)]
    table, results = {}, {}
    for sch in DEMO_SCHEMES:
        tic = time.perf_counter()
        t, states, cov = propagate_recording(data, state0, P0, noise, sch, dtype, progress=progress)
        results[sch] = (states, cov, time.perf_counter() - tic)
        err = io.trajectory_errors(t, states, gt, cov)
        table[sch] = {s: err.at(s, data.t[0]) for s in report_at}
    print(f"\n{'scheme':<10}" + "".join(f"{f'{s} s':>22}" for s in report_at), file=out)
    print(f"{'':<10}" + "".join(f"{'pos m / vel m/s / °':>22}" for _ in report_at), file=out)
    for sch, rows in table.items():
        cells = "".join(f"{f'{a:.3f} / {b:.3f} / {c:.2f}':>22}" for a, b, c in rows.values())
        print(f"{sch:<10}{cells}", file=out)
    horizon = report_at[-1]
    pos = table[scheme][horizon][0]
    print(
        f"\n{scheme}: position drift {pos:.2f} m after {horizon} s ({pos / horizon:.3f} m per "
        f"second on average); propagation with covariance took {results[scheme][2]:.2f} s "
        "including compilation",
        file=out,
    )
    if plot:
        states, cov, _ = results[scheme]

        def make():

            return plot_trajectory(
                data.t,
                states,
                gt,
                cov,
                label=f"jaximu {scheme}",
                title="jaximu: IMU dead reckoning on EuRoC MAV V1_02_medium (real ADIS16448 data)",
            )

        with contextlib.redirect_stdout(out):
            save_plot(make, plot)
    return table
