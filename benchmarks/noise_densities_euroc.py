"""Noise densities of the EuRoC ADIS16448 fitted on each sequence alone, and held-out χ²/dof.

    python benchmarks/noise_densities_euroc.py SEQ_DIR [SEQ_DIR ...] [--lengths 0.25,1,4]
                                               [--fit-fraction 0.6] [--json OUT]

Each sequence (a EuRoC folder ``jaximu.io.read_euroc`` reads; pose-only ground truth gets
its positions' central differences as velocities) is split in time: the first
``--fit-fraction`` fits the biases, the four densities and the reference's σ
(``calibrate`` on ``calibration_problem(..., window_lengths=...)``, midpoint); the rest is
held out. On the held-out part the biases are refitted with the densities fixed (nuisance;
6 parameters against thousands of residuals), once with the fitted densities and once with
the datasheet's (ADIS16448: 1.6968e-4 rad/s/√Hz, 2.0e-3 m/s²/√Hz, 1.9393e-5 rad/s²/√Hz,
3.0e-3 m/s³/√Hz), both with the fitted reference σ; printed: the fitted densities ± 1σ and
both held-out χ²/dof (the whitened innovations of the filter over the held-out windows; the
target for the fitted values: [0.8, 1.25]), and per window length the held-out windows'
mean squared residual, each whitened by its own marginal covariance.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaximu  # noqa: E402
from jaximu import calibration as cal  # noqa: E402
from jaximu.calibration import _noise_fit as cn  # noqa: E402
from jaximu.io import read_euroc  # noqa: E402

DATASHEET = jaximu.ImuNoise.euroc()


def problem(d, gt, noise, lengths, ref_sigma, lo, hi):
    sel = np.flatnonzero((d.t >= lo) & (d.t <= hi) & (d.t >= gt.t[0]) & (d.t <= gt.t[-1]))
    ref = cal.Reference(gt.t, gt.q, gt.p, gt.v)
    return cal.calibration_problem(
        d.t[sel],
        d.gyro[sel],
        d.accel[sel],
        ref,
        noise,
        window_lengths=lengths,
        scheme="midpoint",
        reference_sigma=ref_sigma,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--lengths", default="0.25,1,4")
    ap.add_argument("--fit-fraction", type=float, default=0.6)
    ap.add_argument("--json")
    args = ap.parse_args()
    lengths = tuple(float(x) for x in args.lengths.split(","))
    out = []
    for path in args.sequences:
        tic = time.perf_counter()
        d = read_euroc(path)
        gt = d.ground_truth
        t0, t1 = max(d.t[0], gt.t[0]), min(d.t[-1], gt.t[-1])
        split = t0 + args.fit_fraction * (t1 - t0)
        fit_p = problem(d, gt, DATASHEET, lengths, (1e-3, 1e-3, 1e-2), t0, split)
        res = cal.calibrate(
            fit_p, estimate=("b_g", "b_a") + cal.NOISE_FIELDS, max_reduced_chi2=None
        )
        fitted = jaximu.ImuNoise(*cn._isotropic(res.noise))
        held, by_length = {}, {}
        for label, noise in (("fitted", fitted), ("datasheet", DATASHEET)):
            hp = problem(d, gt, noise, lengths, res.reference_sigma, split, t1)
            hr = cal.calibrate(hp, estimate=("b_g", "b_a"), max_reduced_chi2=None)
            held[label] = hr.reduced_chi2
            by_length[label] = list(hr.chi2_by_length)
        row = {
            "sequence": pathlib.Path(path).name,
            "fit_chi2_dof": res.reduced_chi2,
            "densities": cn._isotropic(res.noise).tolist(),
            "densities_std": cn._isotropic(res.noise_std).tolist(),
            "reference_sigma": res.reference_sigma.tolist(),
            "reference_sigma_std": res.reference_sigma_std.tolist(),
            "heldout_chi2_dof_fitted": held["fitted"],
            "heldout_chi2_dof_datasheet": held["datasheet"],
            "heldout_by_length_fitted": by_length["fitted"],
            "heldout_by_length_datasheet": by_length["datasheet"],
            "seconds": time.perf_counter() - tic,
        }
        out.append(row)
        print(f"\n== {row['sequence']} ({row['seconds']:.0f} s)")
        print(res.noise_table(allan=DATASHEET).replace("Allan", "sheet"))
        print(
            f"held-out χ²/dof: fitted {held['fitted']:.3f}, datasheet {held['datasheet']:.3f}",
            flush=True,
        )
        for label in ("fitted", "datasheet"):
            print(
                f"held-out, each window alone, per length ({label}): "
                + ", ".join(f"{x:g} s: {c:.3f}" for x, c in zip(lengths, by_length[label]))
            )
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
