"""How much of a model's validation error is one constant residual gyro bias?

    python benchmarks/learning_residual_bias.py --data DIR... [--model euroc] [--json FILE]

For each sequence folder (its validation part, after the first 80 s, as
:func:`jaximu.learning.split` cuts it), the corrected gyro of the model (run over the whole
recording, so its causal network sees the samples before the validation part) and the
constant-bias baseline are integrated open loop from the first true attitude of the
validation part. Each is integrated again with the constant residual bias ``δb`` (3,) that
best explains its attitude errors, fitted by least squares on the part itself: an oracle,
not a method. The gap between the two rows says what a better estimate of each recording's
bias could gain, and what remains (noise, scale, the ground truth's own error) whatever the
bias. ``gt − b̄`` is the ground truth's mean bias minus the model's constant where the ground
truth has biases.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402

from jaximu import learning  # noqa: E402
from jaximu.learning.evaluation import integrate_attitude, orientation_errors  # noqa: E402


@jax.jit
def _errors(gyro, q_true, dt, db):
    r, aoe, _ = orientation_errors(integrate_attitude(q_true[0], gyro - db, dt), q_true)
    return r, aoe


def _with_oracle(gyro, q_true, dt):
    """``(mean AOE [deg], mean AOE with the fitted δb [deg], δb [rad/s])``."""
    gyro = jnp.asarray(gyro)
    mean = lambda db: float(np.degrees(np.mean(_errors(gyro, q_true, dt, jnp.asarray(db))[1])))  # noqa: E731
    fit = scipy.optimize.least_squares(
        lambda db: np.asarray(_errors(gyro, q_true, dt, jnp.asarray(db))[0]).ravel(),
        np.zeros(3),
        x_scale=1e-3,
    )
    return mean(np.zeros(3)), mean(fit.x), fit.x


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="sequence folders")
    ap.add_argument("--model", default="euroc", help="a model folder, or 'euroc' (shipped)")
    ap.add_argument("--json", help="write the table here")
    a = ap.parse_args(argv)
    model = learning.pretrained(a.model) if a.model == "euroc" else learning.load(a.model)
    model = model.astype(jnp.float64)
    b_bar = np.asarray(model.config.gyro_bias)
    rows = []
    print(f"{'sequence':26s} {'samples':>7s}  {'':13s} {'AOE':>6s} {'oracle':>6s}  δb [mrad/s]")
    for folder in a.data:
        seq = learning.load_sequence(folder)
        _, val = learning.split(seq)
        k = len(seq) - len(val)
        corrected = np.asarray(model(jnp.asarray(seq.gyro), jnp.asarray(seq.accel)).gyro)[k:]
        q_true, dt = jnp.asarray(val.q), jnp.asarray(np.diff(val.t))
        row = {"name": seq.name, "samples": len(val)}
        for label, gyro in (("constant_bias", val.gyro - b_bar), ("learned", corrected)):
            aoe, oracle, db = _with_oracle(gyro, q_true, dt)
            row[label] = {
                "aoe_mean_deg": aoe,
                "oracle_aoe_mean_deg": oracle,
                "residual_bias_mrad_s": (db * 1e3).tolist(),
            }
            print(
                f"{seq.name:26s} {len(val):7d}  {label:13s} {aoe:6.2f} {oracle:6.2f}  "
                f"{np.round(db * 1e3, 2)}"
            )
        if val.b_g is not None:
            row["gt_minus_constant_mrad_s"] = ((val.b_g.mean(0) - b_bar) * 1e3).tolist()
            print(f"{'':26s} {'':7s}  gt − b̄ {np.round(row['gt_minus_constant_mrad_s'], 2)}")
        rows.append(row)
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps({"sequences": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
