"""``jaximu demo``: dead reckoning on the bundled EuRoC excerpt with every scheme (the work is
:func:`jaximu.recording.run_demo`'s)."""

from __future__ import annotations

from jaximu.app.common import UsageError, check_outputs
from jaximu.studies.recording import DEMO_SCHEMES, DEMO_SECONDS, run_demo


def cmd_demo(args):
    if not args.seconds > 0:
        raise UsageError("--seconds must be positive")
    if not args.seconds <= DEMO_SECONDS:
        raise UsageError(
            f"--seconds {args.seconds:g}: the bundled excerpt holds {DEMO_SECONDS:g} s "
            f"of ground truth; pass --seconds ≤ {DEMO_SECONDS:g}"
        )
    if not args.no_plot:
        check_outputs(plot=args.plot)
    run_demo(
        args.seconds,
        args.scheme,
        None if args.no_plot else args.plot,
        progress=not args.no_progress,
    )
    return 0


def add_parser(sub):
    """Register ``jaximu demo`` on the command's subparsers."""
    p = sub.add_parser(
        "demo",
        help="dead reckoning on bundled real EuRoC data, with a plot",
        description="Propagate the bundled 20 s EuRoC MAV V1_02_medium excerpt "
        "from the ground-truth state with the ground-truth biases, with every "
        "scheme; print the drift against ground truth; write a plot.",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=20.0,
        help="length to propagate, 0 < s ≤ 20 (the excerpt's ground truth)",
    )
    p.add_argument("--scheme", default="midpoint", choices=DEMO_SCHEMES)
    p.add_argument("--plot", default="jaximu_demo.png", help="output PNG (default: %(default)s)")
    p.add_argument("--no-plot", action="store_true", help="do not write a plot")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demo)
    return p
