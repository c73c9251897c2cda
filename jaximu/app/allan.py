"""``jaximu allan``: the Allan deviation of a static recording and its Kalibr noise
densities (the work is :mod:`jaximu.allan`'s: :func:`~jaximu.allan.motion_ratio`,
:func:`~jaximu.allan.allan_deviation`, :func:`~jaximu.allan.fit_noise`,
:func:`~jaximu.allan.check_units`)."""

from __future__ import annotations

import numpy as np

from jaximu.app.common import UsageError, add_input_options, check_outputs, load_recording
from jaximu.studies.recording import save_plot as _plot_or_say


def cmd_allan(args):
    from jaximu.studies import allan

    check_outputs(plot=args.plot)
    data = load_recording(args)
    dt = float(np.median(data.dt))
    jitter = float(np.max(np.abs(data.dt - dt)) / dt)
    if jitter > 0.05:
        print(
            f"note: sample intervals vary by up to {100 * jitter:.0f}% of the median; the "
            "Allan deviation assumes a constant rate"
        )
    # Static means the gyro is white noise about its bias: 1 s means vary √(rate) times less
    # than the samples (≈ 0.07 at 200 Hz); motion varies slowly and survives the averaging.
    # (The spread of the samples cannot tell: a still gyro in deg/s spreads 57× more.)
    moving = allan.motion_ratio(data.gyro, dt)
    static = not moving >= allan.STATIC_MOTION_RATIO  # NaN (too short to judge): static
    if not static:
        print(
            f"note: the gyro's 1 s means vary by {100 * moving:.0f}% of its sample spread: the "
            "recording does not look static, so the densities below include motion"
        )
    print(f"Allan deviation of {len(data)} samples ({data.duration:.1f} s at {1 / dt:.1f} Hz)")
    for name, y in (("gyro", data.gyro), ("accelerometer", data.accel)):
        flat = np.flatnonzero(np.ptp(y, axis=0) == 0)
        if len(flat):
            raise UsageError(
                f"the {name}'s {'xyz'[flat[0]]} axis is constant in {args.file} "
                f"({y[0, flat[0]]:g} in every sample): the Allan deviation measures "
                "noise, and this signal has none (a simulated or quantised file?)"
            )
    results = {}
    for name, y, unit in (("gyroscope", data.gyro, "rad/s"), ("accelerometer", data.accel, "m/s²")):
        taus, adev = allan.allan_deviation(y, dt)
        fit = allan.fit_noise(taus, adev)
        results[name] = (taus, adev, fit, unit)
    if static and not args.no_unit_check:  # motion would inflate the densities
        allan.check_units(results["gyroscope"][2], results["accelerometer"][2])

    def shown(values, determined):  # a density the fit could not determine is no 0
        pairs = zip(np.atleast_1d(values), np.atleast_1d(determined))
        return "[" + " ".join(f"{v:.4g}" if ok else "not-determined" for v, ok in pairs) + "]"

    for name, (_taus, _adev, fit, unit) in results.items():
        print(
            f"{name}_noise_density: {shown(fit.white, fit.white_determined)}"
            f"   # {unit}/√Hz (x, y, z)"
        )
        print(
            f"{name}_random_walk:   {shown(fit.random_walk, fit.random_walk_determined)}"
            f"   # {unit}·√Hz"
        )
    if not all(
        np.all(f.white_determined) and np.all(f.random_walk_determined)
        for _, _, f, _ in results.values()
    ):
        print(
            "note: not-determined: the Allan deviation does not show that term on that axis "
            "(motion, or too short a recording); no density is given for it"
        )
    if data.duration < 600:
        print(
            "note: random walks need a long static recording (hours); this one is "
            f"{data.duration:.0f} s, so they are rough"
        )

    def make():
        import matplotlib.pyplot as plt

        from jaximu.studies.plots import plot_allan

        fig, axes = plt.subplots(1, 2, figsize=(13, 5))
        for ax, (name, (taus, adev, fit, unit)) in zip(axes, results.items()):
            plot_allan(taus, adev, fit, ax=ax, unit=unit, title=f"{name}")
        fig.tight_layout()
        return fig

    _plot_or_say(make, args.plot)
    return 0


def add_parser(sub):
    """Register ``jaximu allan`` on the command's subparsers."""
    p = sub.add_parser(
        "allan",
        help="Allan deviation and noise densities of a static recording",
        description="Overlapping Allan deviation of the gyro and accelerometer, "
        "and the fitted white-noise and random-walk densities (Kalibr units).",
    )
    add_input_options(p)
    p.add_argument("--plot", metavar="PNG", help="write a plot")
    p.set_defaults(func=cmd_allan)
    return p
