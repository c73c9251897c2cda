"""A learned gyro correction, trained through jaximu's preintegration, on real EuRoC data.

Without arguments: the model shipped with ``jaximu[learning]`` (trained on the EuRoC
training sequences) corrects the bundled 20 s excerpt of V2_01_easy; the excerpt is
integrated open loop from its first true attitude with the raw gyro, with the constant bias
stored in the model, and with the learned correction, and the orientation errors and the
consistency of the learned uncertainty are printed.

With sequence folders (EuRoC's ASL layout, or ``imu.csv`` with ``groundtruth.csv`` or
``groundtruth_pose.txt``) it trains a model on them first (what ``jaximu learn train``
does), then evaluates it on the same folders' validation parts::

    python examples/learned_correction.py [--train DIR ...] [--steps N]
"""

import argparse
import pathlib

from jaximu import learning

BUNDLED = pathlib.Path(learning.__file__).parent.parent / "data" / "euroc_v2_01_easy"


def report(model, seq):
    rep = learning.evaluate_sequence(model, seq)
    print(f"{rep.name}: {rep.seconds:.1f} s open loop from the true attitude")
    for key, label in (
        ("raw", "raw gyro"),
        ("constant_bias", "minus the constant bias"),
        ("tracker", "minus the tracked bias alone"),
        ("learned", "learned correction"),
    ):
        if key not in rep.metrics:  # a model without the tracker
            continue
        m = rep.metrics[key]
        print(
            f"  {label:26} mean AOE {m.aoe_mean:6.2f}°  RMSE {m.aoe_rmse:6.2f}°  "
            f"mean AYE {m.aye_mean:6.2f}°"
        )
    print(
        f"  learned uncertainty: average NEES {rep.nees_orientation:.2f} (3 if consistent), "
        f"{100 * rep.inside_3sigma:.0f}% of samples inside 3σ"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", nargs="+", metavar="DIR", help="train on these sequence folders")
    ap.add_argument("--steps", type=int, default=None, help="training steps")
    args = ap.parse_args(argv)
    if args.train:
        seqs = [learning.load_sequence(d) for d in args.train]
        cfg = (
            learning.TrainConfig() if args.steps is None else learning.TrainConfig(steps=args.steps)
        )
        model = learning.train(seqs, cfg).model
        for s in seqs:
            report(model, learning.split(s, cfg.train_seconds)[1])
    else:
        report(learning.pretrained("euroc"), learning.load_sequence(BUNDLED))


if __name__ == "__main__":
    main()
