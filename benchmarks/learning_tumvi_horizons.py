"""What the increment loss can see: the raw gyro's increment residuals against the ground
truth by horizon, beside the ground truth's own noise.

    python benchmarks/learning_tumvi_horizons.py --data DIR... [--horizons 16 32 ...]
        [--seconds 80] [--json FILE]

For each recording (its first ``--seconds``, the training part) the raw gyro (minus
nothing: a calibrated export) is integrated over consecutive windows of ``H`` samples and
compared with the ground truth's increment over the same window (windows with a reference
at both ends only, as the loss does): RMS per axis of ``Log(ΔR_trueᵀ ΔR̂)`` [mrad], and the
mean residual turned into a rate (``mean / (H dt)`` [rad/s], what a constant bias would
explain). A residual flat in ``H`` at ``√2 σ_ref`` is the ground truth's noise, which no
correction of the samples can reduce; what grows with ``H`` is the gyro's error, which the
network can learn.
"""

from __future__ import annotations

import argparse
import json

import jax.numpy as jnp
import numpy as np

from jaximu import learning
from jaximu.learning import losses
from jaximu.learning.evaluation import integrate_attitude


def residuals(seq, H: int):
    """``(W, 3)`` rotation residuals [rad] of the raw gyro over windows of ``H`` samples
    with a reference at both ends."""
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    q_hat = integrate_attitude(f(seq.q[0]), f(seq.gyro), f(seq.dt))
    q = f(seq.q)
    n = min(q.shape[0], q_hat.shape[0])
    d_true = losses.true_increments(q[:n], H)
    d_hat = losses.true_increments(q_hat[:n], H)
    r = np.asarray(losses.rotation_residual(d_true, d_hat))
    ref = np.asarray(seq.has_reference)[:n]
    m = np.asarray(losses.window_references(jnp.asarray(ref), H))[: len(r)]
    return r[: len(m)][m]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--horizons", nargs="+", type=int, default=[16, 32, 64, 128, 256, 512, 1024])
    ap.add_argument("--seconds", type=float, default=80.0)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    out = {}
    for p in a.data:
        seq, _ = learning.split(learning.load_sequence(p), a.seconds)
        rows = {}
        for H in a.horizons:
            r = residuals(seq, H)
            rows[H] = {
                "windows": int(len(r)),
                "rms_mrad": [round(float(x), 2) for x in 1e3 * np.sqrt((r**2).mean(0))],
                "mean_rate_mrad_s": [
                    round(float(x), 3) for x in 1e3 * r.mean(0) / (H / seq.rate_hz)
                ],
            }
            print(seq.name, H, rows[H], flush=True)
        out[seq.name] = rows
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
