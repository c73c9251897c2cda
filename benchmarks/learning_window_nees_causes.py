"""What the windowed orientation NEES of a recording misses: the errors of windows each
integrated open loop from the true attitude with a model's corrected gyro, against the
candidate error shapes a user of the field would consider (plain numpy and scipy, on the
model's corrected gyro and the recording's ground truth; nothing is fitted into the model).

    python benchmarks/learning_window_nees_causes.py MODEL --test DIR --others DIR... [--json FILE]

For each recording (``--test`` and ``--others``):

* ``time_offset``: the time offset ``δ`` between the ground truth and the IMU per 5 s segment,
  by least squares of the ground truth's body rate minus the corrected gyro (both smoothed
  over 50 ms, each segment's mean removed) on the gyro's angular acceleration
  (``ω_gt(t) ≈ ω(t + δ)``), with the share of that rate difference it explains;
* ``shifted_reference``: the root-mean-square window error at 0.1 / 1 / 5 s with the ground
  truth as it is and shifted by that ``δ(t)`` (a drifting offset between the motion capture's
  and the IMU's clocks shows as errors that shrink once it is removed);
* ``error_model``: the windows' mean squared error (windows of 0.2 … 5 s) over what a
  squared-error model fitted (non-negative least squares) on the *other* recordings predicts,
  for terms ``t`` (white gyro noise), ``t²`` (a bias), ``|ω₀|² + |ω₁|²`` (a reference error
  proportional to the rate at the window's two ends: timing noise) and ``∫|ω|² dt`` (a white
  scale-factor noise); 1 where the pooled model transfers.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax.numpy as jnp
import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation, Slerp

from jaximu import learning

TERMS = ("t", "t^2", "|w0|^2+|w1|^2", "int |w|^2 dt")
MODELS = {"t, t^2": [0, 1], "t, t^2, ends": [0, 1, 2], "t, t^2, ends, int": [0, 1, 2, 3]}


def load(model, path):
    s = learning.load_sequence(path)
    c = model(jnp.asarray(s.gyro, jnp.float32), jnp.asarray(s.accel, jnp.float32))
    R = Rotation.from_quat(np.roll(np.asarray(s.q, np.float64), -1, axis=1))
    ref = s.has_reference if s.reference is not None else np.ones(len(s), bool)
    return s, np.asarray(c.gyro, np.float64), np.asarray(s.dt, np.float64), R, ref


def window_errors(g, dt, R, ref, seconds, rate):
    n = int(round(seconds * rate))
    i0 = np.arange(0, len(g) - 1 - n, n)
    i0 = i0[ref[i0] & ref[i0 + n]]
    Rh = R[i0]
    for k in range(n):
        Rh = Rh * Rotation.from_rotvec(g[i0 + k] * dt[i0 + k, None])
    return i0, n, (R[i0 + n].inv() * Rh).as_rotvec()


def time_offset(g, dt, R, t, seg_s=5.0):
    rate_gt = (R[:-1].inv() * R[1:]).as_rotvec() / dt[:, None]
    mid = 0.5 * (g[:-1] + g[1:])
    d = uniform_filter1d(rate_gt - mid, 10, axis=0)
    acc = uniform_filter1d(np.gradient(mid, axis=0) / dt.mean(), 10, axis=0)
    seg = int(seg_s / dt.mean())
    rows = []
    for a in range(0, len(d) - seg, seg):
        y = (d[a : a + seg] - d[a : a + seg].mean(0)).ravel()
        x = acc[a : a + seg].ravel()
        delta = (x @ y) / (x @ x)
        rows.append(
            (float(t[a + seg // 2]), delta, 1 - ((y - delta * x) @ (y - delta * x)) / (y @ y))
        )
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model")
    p.add_argument("--test", required=True, metavar="DIR")
    p.add_argument("--others", nargs="+", required=True, metavar="DIR")
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args()
    model = learning.load(args.model)
    doc: dict = {"model": args.model, "recordings": {}}
    sq: dict = {}
    for path in [args.test, *args.others]:
        s, g, dt, R, ref = load(model, path)
        t = s.t - s.t[0]
        out: dict = {}
        rows = time_offset(g, dt, R, t)
        ds = np.array([r[1] for r in rows])
        out["time_offset_ms"] = {
            "per_5s_segment": [round(r[1] * 1e3, 2) for r in rows],
            "explained_share": [round(r[2], 2) for r in rows],
            "min": float(ds.min() * 1e3),
            "max": float(ds.max() * 1e3),
            "std": float(ds.std() * 1e3),
        }
        shifted = Slerp(t, R)(np.clip(t - np.interp(t, [r[0] for r in rows], ds), t[0], t[-1]))
        out["shifted_reference_rms_deg"] = {}
        for w in (0.1, 1.0, 5.0):
            pair = [
                float(
                    np.degrees(
                        np.sqrt(
                            np.mean(np.sum(window_errors(g, dt, RR, ref, w, s.rate_hz)[2] ** 2, 1))
                        )
                    )
                )
                for RR in (R, shifted)
            ]
            out["shifted_reference_rms_deg"][f"{w:g}s"] = {"as_is": pair[0], "shifted": pair[1]}
        w2 = np.concatenate([[0], np.cumsum(np.sum(g**2, 1) * dt.mean())])
        sq[s.name] = []
        for w in (0.2, 0.5, 1.0, 2.0, 5.0):
            i0, n, r = window_errors(g, dt, R, ref, w, s.rate_hz)
            X = np.stack(
                [
                    np.full(len(i0), w),
                    np.full(len(i0), w**2),
                    np.sum(g[i0] ** 2, 1) + np.sum(g[i0 + n] ** 2, 1),
                    w2[i0 + n] - w2[i0],
                ],
                1,
            )
            sq[s.name].append((w, np.sum(r**2, 1), X))
        doc["recordings"][s.name] = out
        print(
            s.name, json.dumps(out["time_offset_ms"]), json.dumps(out["shifted_reference_rms_deg"])
        )
    for name in sq:
        others = [m for m in sq if m != name]
        row: dict = {}
        for label, cols in MODELS.items():
            y = np.concatenate([e for m in others for _, e, _ in sq[m]])
            A = np.concatenate([X[:, cols] for m in others for _, _, X in sq[m]])
            wt = np.concatenate(
                [np.full(len(e), 1 / (len(e) * e.mean())) for m in others for _, e, _ in sq[m]]
            )
            coef, _ = nnls(A * wt[:, None], y * wt)
            row[label] = {
                "coefficients": dict(zip([TERMS[c] for c in cols], map(float, coef))),
                "observed_over_predicted": {
                    f"{w:g}s": float(e.mean() / (X[:, cols] @ coef).mean()) for w, e, X in sq[name]
                },
            }
            print(
                name,
                label,
                {k: round(v, 2) for k, v in row[label]["observed_over_predicted"].items()},
            )
        doc["recordings"][name]["error_model_fitted_on_the_others"] = row
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
