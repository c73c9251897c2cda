"""``jaximu learn``: train a gyro denoiser on sequences with ground truth, and evaluate one.

  jaximu learn train DIR [DIR ...] --out MODEL [--seed S] [--minutes M] [--steps N]
                     [--learning-rate RATE] [--validate-every STEPS]
                     [--accel-head] [--accel-network] [--no-bias-tracking] [--leave-one-out]
                     [--leave-one-out-worst] [--bias-markov] [--velocity-sigma M_PER_S]
                     [--align-reference]
  jaximu learn evaluate MODEL DIR [DIR ...] [--json FILE] [--plot FILE]

Both take ``--max-gap SECONDS``: the longest ground-truth gap bridged by interpolation at the
IMU samples (samples in longer gaps, motion-capture dropouts, have no reference), and
the readers' units and repairs of the IMU samples (``--sort``, ``--drop-duplicates``, …).

Parsing and printing only: the work is :mod:`jaximu.learning`'s. Needs
``pip install "jaximu[learning]"`` (equinox).
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import numpy as np

from jaximu.app.common import (
    UsageError,
    add_repair_options,
    add_unit_options,
    check_outputs,
    reader_options,
)
from jaximu.io import DataError

LEARNING_EXTRA = 'the learning commands need equinox: pip install "jaximu[learning]"'


def _learning():
    try:
        import equinox  # noqa: F401
    except ImportError:
        raise ImportError(LEARNING_EXTRA) from None
    from jaximu import learning

    return learning


def _check_model_out(path):
    p = pathlib.Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"--out {p} is a file; a model is saved as a folder: give a new name")
    if p.is_dir() and any(p.iterdir()) and not (p / "model.json").is_file():
        raise UsageError(
            f"--out {p} is a folder that holds other files, not a jaximu model; give "
            "a new or empty folder (nothing was written)"
        )
    if not p.parent.exists():
        raise UsageError(f"--out {p}: the folder {p.parent} does not exist; create it first")
    return p


def _load_all(learning, args):
    if args.max_gap is not None and not args.max_gap > 0:  # inf: any gap; NaN refused
        raise UsageError(
            f"--max-gap must be a positive number of seconds (inf: any gap), got {args.max_gap:g}"
        )
    paths = [pathlib.Path(d) for d in args.dirs]
    for p in paths:
        if not p.exists():
            raise UsageError(f"sequence folder {p} does not exist")
    resolved = [p.resolve() for p in paths]
    for i, r in enumerate(resolved):
        if r in resolved[:i]:
            raise UsageError(f"sequence folder {paths[i]} is given twice: give each once")
    # a sequence is named by its folder, or by the path given where two folders share a name
    # (data/a/V1_01_easy and data/b/V1_01_easy): the training record is keyed by name
    basenames = [p.name for p in paths]
    options = reader_options(args, max_gap=False)
    seqs = []
    for p in paths:
        name = p.name if basenames.count(p.name) == 1 else str(p)
        seq = learning.load_sequence(p, name=name, max_gap=args.max_gap, **options)
        for note in seq.repairs:
            print(f"repair: {p}: {note}", file=sys.stderr)
        if seq.reference is not None:
            gaps = np.diff(seq.stamps()[0])
            print(
                f"{seq.name}: {np.sum(~seq.reference)} IMU samples fall in ground-truth "
                f"dropouts (the longest {gaps.max():.2f} s): no reference there, no error "
                "measured across them"
            )
        seqs.append(seq)
    return seqs


def cmd_train(args):
    learning = _learning()
    out = _check_model_out(args.out)
    if args.minutes is not None and not (np.isfinite(args.minutes) and args.minutes > 0):
        raise UsageError(f"--minutes must be a positive number, got {args.minutes:g}")
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps must be a positive integer, got {args.steps}")
    if args.learning_rate is not None and not (
        np.isfinite(args.learning_rate) and 0 < args.learning_rate < 1
    ):
        raise UsageError(
            "--learning-rate must be a positive number below 1 (AdamW's first rate, e.g. "
            f"0.003 or 0.001), got {args.learning_rate:g}"
        )
    if args.validate_every is not None and args.validate_every < 1:
        raise UsageError(
            f"--validate-every must be a positive number of steps, got {args.validate_every}"
        )
    if args.velocity_sigma is not None:
        if args.no_bias_tracking:
            raise UsageError(
                "--velocity-sigma sets the gyro-bias tracker's velocity bound, and "
                "--no-bias-tracking turns the tracker off: leave one of the two flags out"
            )
        if not (np.isfinite(args.velocity_sigma) and args.velocity_sigma > 0):
            raise UsageError(
                "--velocity-sigma must be a positive number of m/s (the tracker's bound on "
                f"the true velocity, e.g. 1 or 3), got {args.velocity_sigma:g}"
            )
    flag = "--leave-one-out-worst" if args.leave_one_out_worst else "--leave-one-out"
    if (args.leave_one_out or args.leave_one_out_worst) and len(args.dirs) < 2:
        raise UsageError(
            f"{flag} needs two sequence folders or more (each is validated by "
            "models trained on the others): give more folders or leave the flag out"
        )
    if args.accel_network and (args.leave_one_out or args.leave_one_out_worst):
        raise UsageError(
            f"--accel-network keeps the accelerometer's layers by the validation parts' "
            f"windows, and {flag} chooses the step by the attitude of recordings left out: "
            "leave one of the two flags out"
        )
    t0 = time.perf_counter()
    seqs = _load_all(learning, args)
    settings = {} if args.steps is None else {"steps": args.steps}
    if args.leave_one_out or args.leave_one_out_worst:
        settings["selection"] = (
            "leave_one_out_worst" if args.leave_one_out_worst else "leave_one_out"
        )
    if args.bias_markov:
        settings["bias_markov"] = True
    if args.learning_rate is not None:  # the cosine annealing's floor a tenth of it
        settings.update(learning_rate=args.learning_rate, min_learning_rate=args.learning_rate / 10)
    if args.validate_every is not None:
        settings["validate_every"] = args.validate_every
    if args.align_reference:
        settings["align_reference"] = True
    cfg = learning.TrainConfig(**settings)
    print(f"read {len(seqs)} sequences in {time.perf_counter() - t0:.1f} s")
    tracker = {} if args.velocity_sigma is None else {"velocity_sigma": args.velocity_sigma}
    mcfg = learning.ModelConfig(
        accel_head=args.accel_head or args.accel_network,
        accel_network=args.accel_network,
        bias_tracking=not args.no_bias_tracking,
        **tracker,
    )
    result = learning.train(seqs, cfg, mcfg, seed=args.seed, minutes=args.minutes)
    record = dict(result.record)
    record["command"] = "jaximu learn train " + " ".join(
        [pathlib.Path(d).name for d in args.dirs]
        + ["--out", out.name, "--seed", str(args.seed)]
        + (["--steps", str(args.steps)] if args.steps else [])
        + (["--learning-rate", f"{args.learning_rate:g}"] if args.learning_rate else [])
        + (["--validate-every", str(args.validate_every)] if args.validate_every else [])
        + (["--accel-head"] if args.accel_head else [])
        + (["--accel-network"] if args.accel_network else [])
        + (["--no-bias-tracking"] if args.no_bias_tracking else [])
        + (
            ["--velocity-sigma", f"{args.velocity_sigma:g}"]
            if args.velocity_sigma is not None
            else []
        )
        + (["--leave-one-out"] if args.leave_one_out and not args.leave_one_out_worst else [])
        + (["--leave-one-out-worst"] if args.leave_one_out_worst else [])
        + (["--bias-markov"] if args.bias_markov else [])
        + (["--align-reference"] if args.align_reference else [])
        + (["--max-gap", f"{args.max_gap:g}"] if args.max_gap is not None else [])
    )
    learning.save(out, result.model, record)
    wall = time.perf_counter() - t0
    print(
        f"saved the model of step {record['best_step']} to {out}; wall time {wall:.0f} s "
        f"(compile ≈ {record['compile_seconds']:.0f} s, training "
        f"{record['wall_seconds'] - record['compile_seconds']:.0f} s)"
    )
    return 0


METHODS = (
    ("raw", "raw gyro"),
    ("constant_bias", "constant bias"),
    ("tracker", "tracker alone"),
    ("learned", "learned"),
)
"""The rows of the table: the tracked bias alone is the model with its network's correction
zeroed, printed beside the model so that what the network adds shows."""


WINDOW_SECONDS = (1.0, 5.0)
"""The windows of the windowed NEES and of the dead reckoning [s]."""


def _window_nees(learning, model, seq):
    """``{"1s": NEES, "5s": NEES}`` of the windows each started from the true attitude that
    ``seq`` holds (a window with no reference at both ends in the whole recording: None)."""
    out = {}
    for w in WINDOW_SECONDS:
        if seq.seconds < w:
            continue
        try:
            out[f"{w:g}s"] = learning.window_nees(model, seq, w)
        except DataError:  # motion-capture dropouts at every window's end
            out[f"{w:g}s"] = None
    return out


def _table(rep, windows=None, nees=None):
    m = rep.metrics
    lines = [
        f"{rep.name}: {rep.samples} samples, {rep.seconds:.1f} s, compared at "
        f"{len(rep.t)} ground-truth stamps",
        f"  {'':16}{'AOE mean':>10}{'AOE RMSE':>10}{'AYE mean':>10}{'AYE RMSE':>10}  [deg]",
    ]
    for key, label in METHODS:
        if key not in m:  # a model without the tracker: no tracker row
            continue
        x = m[key]
        lines.append(
            f"  {label:16}{x.aoe_mean:10.2f}{x.aoe_rmse:10.2f}{x.aye_mean:10.2f}{x.aye_rmse:10.2f}"
        )
    lines.append(
        f"  learned uncertainty: average NEES {rep.nees_orientation:.2f} (3 when "
        f"consistent), {100 * rep.inside_3sigma:.1f}% of samples inside 3σ"
        + (
            "; over windows from the true attitude "
            + ", ".join(f"{w} {'-' if x is None else f'{x:.2f}'}" for w, x in nees.items())
            if nees
            else ""
        )
    )
    for w, row in (windows or {}).items():
        lines.append(
            f"  dead reckoning over {w} windows from the true state, mean |δv| / |δp|: "
            + ", ".join(
                f"{k.replace('_', ' ')} {a:.3f} m/s / {b:.3f} m" for k, (a, b) in row.items()
            )
        )
    return "\n".join(lines)


def cmd_evaluate(args):
    learning = _learning()
    check_outputs(json=args.json, plot=args.plot)  # before any work
    json_out = None if args.json is None else pathlib.Path(args.json)
    plot_out = args.plot
    model = learning.load(args.model)
    where = learning.checkpoint
    print(
        f"model: {args.model} "
        + (
            f"(shipped with jaximu: {where.PRETRAINED[args.model]})"
            if where.shipped(args.model)
            else f"(the folder {pathlib.Path(args.model).resolve()})"
        )
    )
    seqs = _load_all(learning, args)
    for s in seqs:  # every sequence before the first table
        learning.evaluation.check_evaluable(model, s)
    reports, windows, window_nees = [], [], []
    for s in seqs:
        rep = learning.evaluate_sequence(model, s)
        win = (
            {f"{w:g}s": learning.evaluation.window_errors(model, s, w) for w in WINDOW_SECONDS}
            if s.b_g is not None and s.seconds >= max(WINDOW_SECONDS)
            else {}
        )  # velocities measured
        nees = _window_nees(learning, model, s)
        print(_table(rep, win, nees))
        m = rep.metrics
        if m["learned"].aoe_mean > m["raw"].aoe_mean < m["constant_bias"].aoe_mean:
            # the model's stored bias is its training IMU's: on another kind of IMU it
            # starts from a bias the recording does not have (a calibrated IMU's model
            # stores none, and the stored bias then moves nothing)
            print(
                f"  note: the learned correction is worse than the raw gyro on {rep.name}; "
                "is it an IMU of the model's kind (stored gyro bias "
                + " ".join(f"{x:.4f}" for x in model.config.gyro_bias)
                + " rad/s)?"
            )
        reports.append(rep)
        windows.append(win)
        window_nees.append(nees)
    avg = {
        k: float(np.mean([r.metrics[k].aoe_mean for r in reports]))
        for k, _ in METHODS
        if k in reports[0].metrics
    }
    print("average mean AOE [deg]: " + ", ".join(f"{k} {v:.2f}" for k, v in avg.items()))
    if json_out is not None:
        seqs_json = [
            dict(r.to_json(), dead_reckoning=w, window_nees_orientation=n)
            for r, w, n in zip(reports, windows, window_nees)
        ]
        doc = {
            "model": str(args.model),
            "sequences": seqs_json,
            "average_aoe_mean_deg": avg,
            "conventions": {
                "aoe_mean": "mean over the ground truth's stamps of the geodesic angle of "
                "R_gt^T R_est (AirIMU)",
                "tracker": "the tracked gyro bias alone: the model with its network's "
                "correction zeroed",
                "aoe_rmse": "its RMSE (Brossard)",
                "aye": "|yaw| (ZYX Euler) of the world-frame error R_est R_gt^T",
                "nees_orientation": "average r^T S^-1 r, r = Log(R_gt^T R_est)",
                "inside_3sigma": "fraction of samples with NEES <= 14.16",
                "window_nees_orientation": "window -> the average over consecutive windows, "
                "each integrated from the true attitude, of r^T S^-1 r at the window's end, "
                "S the model's covariance over the window (3 when consistent)",
                "dead_reckoning": "window -> variant -> [mean |dv| m/s, mean "
                "|dp| m] over consecutive windows from the true state",
            },
        }
        json_out.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {json_out}")
    if plot_out is not None:
        from jaximu.studies.recording import save_plot

        def make():
            import matplotlib.pyplot as plt

            n = len(reports)
            fig, axes = plt.subplots(n, 1, figsize=(10, 2.6 * n), squeeze=False)
            for ax, r in zip(axes[:, 0], reports):
                ax.plot(r.t, r.aoe["constant_bias"], color="0.6", label="constant bias")
                if "tracker" in r.aoe:
                    ax.plot(r.t, r.aoe["tracker"], color="C1", label="tracker alone")
                ax.plot(r.t, r.aoe["learned"], color="C0", label="learned")
                ax.fill_between(
                    r.t, 0, r.sigma3, color="C0", alpha=0.15, label="learned 3σ (3 √trace S)"
                )
                ax.set_title(r.name)
                ax.set_ylabel("AOE [deg]")
                ax.legend(loc="upper left")
            axes[-1, 0].set_xlabel("time [s]")
            fig.tight_layout()
            return fig

        save_plot(make, str(plot_out))
    return 0


def add_parser(sub):
    """Register ``jaximu learn`` on the command's subparsers."""
    p = sub.add_parser(
        "learn",
        help="train and evaluate a learned gyro denoiser",
        description=__doc__.split("\n\n")[0],
    )
    learn = p.add_subparsers(dest="learn_command", required=True, metavar="ACTION")
    t = learn.add_parser(
        "train",
        help="train on sequence folders with ground truth",
        description="Train the denoiser on sequence folders (EuRoC ASL, or "
        "imu.csv with groundtruth.csv / groundtruth_pose.txt). The first 80 s "
        "of each are for training, the rest for validation; the model with "
        "the lowest validation mean AOE is kept.",
    )
    t.add_argument("dirs", nargs="+", metavar="DIR", help="sequence folders")
    t.add_argument("--out", required=True, metavar="MODEL", help="model folder to write")
    t.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    t.add_argument(
        "--minutes", type=float, help="stop after this wall time, keeping the best model so far"
    )
    t.add_argument("--steps", type=int, help="training steps (default: the recipe's)")
    t.add_argument(
        "--learning-rate",
        type=float,
        metavar="RATE",
        help="AdamW's rate at the start of each cosine period, annealed to a tenth of it "
        "(default: 0.003, to 0.0003)",
    )
    t.add_argument(
        "--validate-every",
        type=int,
        metavar="STEPS",
        help="steps between validations, the steps the kept model is chosen among (default: 25)",
    )
    t.add_argument(
        "--accel-head",
        action="store_true",
        help="also correct the accelerometer, "
        "trained on velocity increments (sequences with ground-truth velocity)",
    )
    t.add_argument(
        "--accel-network",
        action="store_true",
        help="the accelerometer head with convolution layers of its own (implies "
        "--accel-head): the gyro is trained and kept as without it, the accelerometer's "
        "layers kept from the step with the lowest velocity and position errors over the "
        "validation parts' 1-s and 5-s windows",
    )
    t.add_argument(
        "--no-bias-tracking",
        action="store_true",
        help="no gyro-bias tracker: the network corrects the training recordings' constant "
        "bias alone (for a vehicle whose velocity does not stay near zero, or to measure "
        "the network on its own)",
    )
    t.add_argument(
        "--velocity-sigma",
        type=float,
        metavar="M_PER_S",
        help="the gyro-bias tracker's bound on the true velocity, v = 0 ± this [m/s] "
        "(default: 1, chosen on EuRoC's drones, whose gyro bias is unknown to 2e-3 rad/s; "
        "on TUM-VI's calibrated BMI160, 1 makes the tracker worse than the raw gyro, "
        "3 does not: pass 3 there)",
    )
    t.add_argument(
        "--leave-one-out",
        action="store_true",
        help="choose the kept step by leaving each recording out in turn (a model trained "
        "on the others, the left-out one integrated whole) instead of by the later seconds "
        "of the same recordings; trains one model per folder, plus the final one",
    )
    t.add_argument(
        "--bias-markov",
        action="store_true",
        help="after training, fit a Gauss–Markov gyro bias (σ_m, τ) to the validation parts' "
        "1-s and 5-s windows and record their windowed NEES before and with it",
    )
    t.add_argument(
        "--align-reference",
        action="store_true",
        help="train on each recording's ground truth realigned in time to the integrated "
        "gyro, the offset fitted from the raw gyro's increments (the mocap's clock and the "
        "integration's half-interval lag: 3.4 ms on TUM-VI, 0.6-2.8 ms on EuRoC); validation "
        "and evaluation compare with it as recorded (with --no-bias-tracking, on EuRoC's "
        "recordings left out in turn: a mean AOE 0.46 of the constant bias's, 0.71 without it)",
    )
    t.add_argument(
        "--leave-one-out-worst",
        action="store_true",
        help="as --leave-one-out, but keep a trained step only if it is below the untrained "
        "network on every recording left out (the untrained network otherwise)",
    )
    t.set_defaults(func=cmd_train)
    e = learn.add_parser(
        "evaluate",
        help="integrate whole sequences raw, with the constant bias, with the tracker alone "
        "and with the model",
        description="Integrate each whole sequence from its first true "
        "attitude at the IMU rate: raw, minus the constant bias, minus the tracked bias "
        "alone (the model with its network's correction zeroed) and with the model; print "
        "AOE/AYE (mean and RMSE) at the ground truth's own stamps (never across a "
        "motion-capture dropout) and the learned uncertainty's NEES.",
    )
    e.add_argument(
        "model", metavar="MODEL", help="a model folder, or a shipped model: 'euroc' or 'tumvi'"
    )
    e.add_argument("dirs", nargs="+", metavar="DIR", help="sequence folders")
    e.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    e.add_argument("--plot", metavar="FILE", help="plot the orientation error over time")
    e.set_defaults(func=cmd_evaluate)
    for q in (t, e):
        q.add_argument(
            "--max-gap",
            type=float,
            metavar="SECONDS",
            help="the longest ground-truth gap to interpolate the reference at the IMU "
            "samples across (default: 5 × its median interval); samples in longer gaps "
            "(motion-capture dropouts) have no reference: training leaves them out",
        )
        add_unit_options(q.add_argument_group("input"))
        add_repair_options(q, max_gap=False)
    return p
