"""The ``jaximu`` command: IMU recordings in, trajectories, uncertainty and plots out.

  jaximu demo                      dead reckoning on bundled real EuRoC data, with a plot
  jaximu propagate FILE            propagate a recording (EuRoC/TUM-VI folder, CSV, NPZ, ROS bag)
  jaximu preintegrate FILE         preintegrate it between keyframes
  jaximu montecarlo                Monte Carlo covariance study on a simulated trajectory
  jaximu calibrate FILE            fit IMU biases (scale, misalignment, …) against ground truth
  jaximu allan FILE                Allan deviation and Kalibr noise densities of a static recording
  jaximu learn train|evaluate      train and evaluate a learned gyro denoiser (jaximu[learning])

User mistakes (a missing file, a malformed CSV, bad options) end with one line on stderr and
exit code 2; ``jaximu COMMAND --help`` describes each command.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

from jaximu.app import allan, calibrate, demo, learn, montecarlo, preintegrate, propagate
from jaximu.app.common import UsageError, check_earth_rate

__all__ = [
    "API_ONLY_OPTIONS",
    "FLAGS",
    "INVERTED_FLAGS",
    "UsageError",
    "build_parser",
    "cache_folder",
    "enable_compilation_cache",
    "flag_of",
    "main",
    "options_table",
]

SUBCOMMANDS = (demo, propagate, preintegrate, montecarlo, calibrate, allan, learn)
"""The modules of the subcommands, in the order ``jaximu --help`` lists them; each registers
its parser with ``add_parser(sub)``."""


def build_parser():
    """The command's parser: one subparser per module of :data:`SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="jaximu",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    return parser


def options_table() -> str:
    """Markdown of every command's options (flag, accepts, default, help), generated from
    the parser: the "what each function accepts" document embeds it, and a test keeps the
    two equal."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    lines = []
    commands = []
    for name, p in sub.choices.items():  # `jaximu learn train`: a subcommand's actions too
        nested = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        commands += (
            [(f"{name} {n}", q) for a in nested for n, q in a.choices.items()]
            if nested
            else [(name, p)]
        )
    for name, p in commands:
        lines += [
            f"### `jaximu {name}`",
            "",
            "| option | accepts | default | meaning |",
            "|---|---|---|---|",
        ]
        for a in p._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            flag = ", ".join(a.option_strings) or a.dest
            if a.choices:
                accepts = " ".join(f"`{c}`" for c in a.choices)
            elif a.nargs == 0:
                accepts = "flag"
            else:
                accepts = {float: "number", int: "integer"}.get(a.type, "text")
            default = "" if a.default is None or a.nargs == 0 else f"`{a.default}`"
            text = (a.help or "").replace("%(default)s", str(a.default)).replace("|", "/")
            lines.append(f"| `{flag}` | {accepts} | {default} | {text} |")
        lines.append("")
    return "\n".join(lines)


# The library's errors carry their repairs as data (jaximu.errors.Fix: option and value); on
# the command line they are flags.
FLAGS = {
    "gyro_unit": "--gyro-unit",
    "accel_unit": "--accel-unit",
    "time_unit": "--time-unit",
    "sort": "--sort",
    "drop_duplicates": "--drop-duplicates",
    "drop_nonfinite": "--drop-nonfinite",
    "allow_gaps": "--allow-gaps",
    "max_gap": "--max-gap",
    "gravity": "--gravity",
    "keyframe_interval": "--keyframe-interval",
    "seconds": "--seconds",
    "update_every": "--filter",
    "estimate": "--estimate",
    "window_lengths": "--window-lengths",
    "reference_sigma": "--reference-sigma",
    "optimizer": "--optimizer",
    "noise": "--noise",
    "accel_head": "--accel-head",
    "accel_network": "--accel-network",
    "velocity_sigma": "--velocity-sigma",
    "learning_rate": "--learning-rate",
    "validate_every": "--validate-every",
    "align_reference": "--align-reference",
}
INVERTED_FLAGS = {("check_units", False): "--no-unit-check"}
API_ONLY_OPTIONS = frozenset(
    {"measurement", "path", "model", "extrinsics", "kernel", "min_learning_rate", "start"}
)
"""Options the library's fixes may name that have no flag (rendered as keywords):
``monte_carlo``'s ``measurement`` (the command builds it from ``--fix-sigma``),
``MonteCarloResult.save``'s ``path`` (``--save`` is checked by the command first), the
learning settings' ``kernel`` and ``min_learning_rate`` and ``window_errors``' ``start``
(no command sets them)."""


def flag_of(fix) -> str:
    """A :class:`jaximu.errors.Fix` as the command's flag: ``--gyro-unit deg/s``, ``--sort``."""
    from jaximu.errors import ANY

    inverted = INVERTED_FLAGS.get((fix.option, fix.value))
    if inverted:
        return inverted
    flag = FLAGS.get(fix.option)
    if flag is None:
        return fix.as_keyword()
    if fix.value is ANY:
        return fix.describe(flag)
    if fix.value is True:
        return flag
    if fix.value is False:  # a switch to leave off
        return f"no {flag}"
    if isinstance(fix.value, tuple):  # the command's lists are comma-separated numbers
        return f"{flag} " + ",".join(f"{x:g}" for x in fix.value)
    return f"{flag} {fix.value:g}" if isinstance(fix.value, float) else f"{flag} {fix.value}"


def _message(e) -> str:
    from jaximu.errors import InputError

    return e.render(flag_of) if isinstance(e, InputError) else str(e)


def cache_folder(environ=None) -> pathlib.Path | None:
    """Where the command keeps XLA's compilations between runs: ``$JAXIMU_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaximu/xla``, else ``~/.cache/jaximu/xla``; ``None`` when
    ``JAXIMU_CACHE_DIR`` is ``off`` (or empty)."""
    env = os.environ if environ is None else environ
    if "JAXIMU_CACHE_DIR" in env:
        value = env["JAXIMU_CACHE_DIR"].strip()
        return None if value.lower() in ("", "off", "0", "none") else pathlib.Path(value)
    base = env.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
    return pathlib.Path(base) / "jaximu" / "xla"


def enable_compilation_cache() -> pathlib.Path | None:
    """Persist compilations in :func:`cache_folder`, so that a second run
    of a command skips them: ``jaximu calibrate``'s L-BFGS step compiles for ~40 s on 2 CPU
    cores. A folder the user already gave JAX (``JAX_COMPILATION_CACHE_DIR``) is kept.
    Returns the folder in use, or None."""
    import jax

    given = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
    if given:
        return pathlib.Path(given)
    folder = cache_folder()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # every compilation, not only those over 1 s: a command runs ~150 small eager ones
    # (0.05 s each, ~7 s in all for calibrate), which load from the cache in a fraction
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder


def main(argv=None, *, cache: bool | None = None) -> int:
    """The command. ``cache``: keep compilations in :func:`cache_folder` (default: when run
    as the command, ``argv is None``; not when called from Python with ``argv``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from jaximu.io import DataError

    args.cache_dir = None
    try:
        check_earth_rate(args)
        if cache if cache is not None else argv is None:
            args.cache_dir = enable_compilation_cache()
        return args.func(args)
    except (UsageError, DataError, ValueError, ImportError, OSError, OverflowError) as e:
        # user mistakes (and unwritable outputs, full disks): one line, no traceback
        print(f"jaximu {args.command}: error: {_message(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaximu: interrupted", file=sys.stderr)
        return 130
