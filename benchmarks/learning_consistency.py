"""How consistent can a learned gyro uncertainty be, sequence by sequence?

    python benchmarks/learning_consistency.py --data DIR... [--model euroc] [--draws 2000]

For each sequence folder (the EuRoC training sequences; their validation part, after the
first 80 s, as :func:`jaximu.learning.split` cuts it), this prints the average orientation
NEES of the model's open-loop run (:mod:`jaximu.learning.uncertainty`) with the residual
gyro bias ``σ_b`` set on all sequences and on the others (leave-one-out), and compares it
with what a *perfectly consistent* model would give: errors drawn from the model's own
assumptions, by simulating the error state ``[δθ, δb_g]`` through the same per-step
``(Φ, Q)`` (:func:`jaximu.learning.losses.rotation_step_blocks`, the learned per-sample
density, the bias random walk) from a residual bias ``δb ~ N(0, σ_b² I)``, plus the
reference's own noise (one draw at the start, which the run inherits, and one at every
compared sample). Each simulated run's NEES is averaged over its samples as the evaluation
does.

What it shows: over a whole sequence the error is dominated by one draw of the residual bias,
so the per-sequence average NEES of a consistent model is close to ``χ²₃ / 3 · 3`` — one
χ² sample with 3 degrees of freedom, not an average of many. The fraction of consistent runs
whose NEES falls in a band such as ``[1.5, 6]`` is therefore far from 1, and the chance that
all sequences fall in it at once is the product. The printed table gives both for the
sequences given.

A second table reads the learned *per-sample* density where it, not the residual bias,
decides: the NEES of the orientation increments over consecutive windows of 16, 32, 200 and
1000 samples of each validation part, each window integrated from the true attitude at its
start (the windows and covariance of the training loss: :func:`increment_terms`,
:func:`rotation_covariance` with the model's ``σ_b`` and ``σ_ref``). There the NEES is an
average over many windows, so a consistent model gives close to 3 on every sequence where
the windows are many and short (the residual bias, one draw for the whole part, weighs more
in the few long ones).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)  # the simulation's covariance algebra in float64

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaximu import learning  # noqa: E402
from jaximu.learning import uncertainty  # noqa: E402
from jaximu.learning.evaluation import CHI2_3_3SIGMA  # noqa: E402
from jaximu.learning.losses import (  # noqa: E402
    increment_terms,
    nees,
    rotation_covariance,
    rotation_step_blocks,
)

BAND = (1.5, 6.0)
WINDOWS = (16, 32, 200, 1000)


def corrected_part(model, seq, start):
    """The model's corrected samples of ``seq`` from ``start`` on, in float64: the network
    runs in float32 on the whole sequence (the part's first outputs see the samples before
    it), as the evaluation does; what follows it is in float64."""
    c = model(jnp.asarray(seq.gyro, jnp.float32), jnp.asarray(seq.accel, jnp.float32))
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float64)[start:], c)


def step_blocks(model, c, seq, start):
    """The validation part's per-step ``(Φ, Q)`` ``(T-1, 6, 6)`` from its corrected samples
    ``c`` (:func:`corrected_part`)."""
    dt = jnp.asarray(seq.dt, jnp.float64)[start:]
    F, Q = rotation_step_blocks(c.gyro[:-1], c.gyro_density[:-1], dt, model.config.gyro_random_walk)
    return np.asarray(F), np.asarray(Q)


def simulated_nees(F, Q, terms, bias_sigma, draws, rng):
    """``(draws,)`` average NEES of runs drawn from the model's own error model."""
    W, B = np.asarray(terms.W, np.float64), np.asarray(terms.B, np.float64)
    s_ref = float(terms.reference_sigma)
    S = W + bias_sigma**2 * B @ np.swapaxes(B, -1, -2) + 2.0 * s_ref**2 * np.eye(3)
    S_inv = np.linalg.inv(S)
    L = np.linalg.cholesky(Q + 1e-30 * np.eye(6))  # Q's bias rows are exact zeros at times
    x = np.zeros((draws, 6))
    x[:, 3:] = bias_sigma * rng.standard_normal((draws, 3))
    e0 = s_ref * rng.standard_normal((draws, 3))
    total = np.zeros(draws)  # sample 0: r = 0 exactly (the run starts at the true attitude)
    for k in range(F.shape[0]):
        x = x @ F[k].T + rng.standard_normal((draws, 6)) @ L[k].T
        r = x[:, :3] + s_ref * rng.standard_normal((draws, 3)) - e0
        total += np.einsum("ni,ij,nj->n", r, S_inv[k + 1], r)
    return total / (F.shape[0] + 1)


def window_nees(model, c, seq, start, horizons=WINDOWS):
    """``{H: (average NEES, fraction inside 3σ, windows)}`` of the orientation increments
    over consecutive windows of ``H`` samples from ``start``, from the part's corrected
    samples ``c`` (:func:`corrected_part`); horizons with no whole window in the part are
    left out."""
    q = jnp.asarray(seq.q, jnp.float64)[start:]
    dt = float(np.mean(seq.dt))
    sb, sr = float(model.bias_sigma), float(model.reference_sigma)
    out = {}
    for H in horizons:
        if c.gyro.shape[0] // H < 1:
            continue
        ((r, Phi, Q, _),) = increment_terms(
            c, q, dt, (H,), random_walk=model.config.gyro_random_walk
        )
        e = np.asarray(nees(r, rotation_covariance(Phi, Q, sb, sr)))
        out[H] = (float(e.mean()), float(np.mean(e <= CHI2_3_3SIGMA)), int(e.size))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="sequence folders")
    ap.add_argument("--model", default="euroc", help="a model folder or 'euroc' (shipped)")
    ap.add_argument("--draws", type=int, default=2000, help="simulated runs per sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=pathlib.Path, help="write the figures as JSON")
    a = ap.parse_args(argv)
    model = learning.load(a.model)
    seqs = [learning.load_sequence(d) for d in a.data]
    starts = [len(s) - len(learning.split(s)[1]) for s in seqs]
    terms = [uncertainty.nees_terms(model, s, k, jnp.float64) for s, k in zip(seqs, starts)]
    sigma = uncertainty.fit_bias_sigma(terms)
    loo = uncertainty.leave_one_out(terms)
    rng = np.random.default_rng(a.seed)
    rows, inside = [], []
    print(f"σ_b set on all sequences: {sigma:.3g} rad/s; simulated runs per sequence: {a.draws}")
    print(
        f"{'sequence':24s} {'samples':>7s} {'NEES(all)':>9s} {'NEES(LOO)':>9s}   consistent "
        f"model's NEES: 5%    50%    95%  P(in [{BAND[0]:g}, {BAND[1]:g}])"
    )
    parts = [corrected_part(model, s, k) for s, k in zip(seqs, starts)]
    for s, k, c, t, (_, nees_loo) in zip(seqs, starts, parts, terms, loo):
        F, Q = step_blocks(model, c, s, k)
        sim = simulated_nees(F, Q, t, sigma, a.draws, rng)
        p = float(np.mean((sim >= BAND[0]) & (sim <= BAND[1])))
        q5, q50, q95 = np.quantile(sim, [0.05, 0.5, 0.95])
        measured = uncertainty.average_nees(t, sigma)
        inside.append(p)
        rows.append(
            {
                "name": s.name,
                "samples": len(s) - k,
                "nees_all": measured,
                "nees_leave_one_out": nees_loo,
                "consistent_quantiles": [q5, q50, q95],
                "consistent_p_in_band": p,
            }
        )
        print(
            f"{s.name:24s} {len(s) - k:7d} {measured:9.2f} {nees_loo:9.2f}   "
            f"{'':15s}{q5:5.2f}  {q50:5.2f}  {q95:5.2f}  {p:5.2f}"
        )
    joint = float(np.prod(inside))
    print(
        f"a consistent model puts every sequence in [{BAND[0]:g}, {BAND[1]:g}] with probability "
        f"{joint:.2f} (independent sequences)"
    )
    print(
        f"\nNEES of the increments over windows from the true attitude (the model's "
        f"σ_b {float(model.bias_sigma):.3g} rad/s, σ_ref {float(model.reference_sigma):.3g} "
        "rad): average / fraction inside 3σ / windows"
    )
    print(f"{'sequence':24s} " + " ".join(f"{f'{H} samples':>20s}" for H in WINDOWS))
    for s, k, c, row in zip(seqs, starts, parts, rows):
        w = window_nees(model, c, s, k)
        row["window_nees"] = {str(H): v for H, v in w.items()}
        print(
            f"{s.name:24s} "
            + " ".join(
                f"{f'{w[H][0]:.2f} / {w[H][1]:.3f} / {w[H][2]}' if H in w else '-':>20s}"
                for H in WINDOWS
            )
        )
    if a.out:
        a.out.write_text(
            json.dumps(
                {
                    "model": a.model,
                    "bias_sigma": sigma,
                    "band": BAND,
                    "draws": a.draws,
                    "seed": a.seed,
                    "sequences": rows,
                    "p_all_in_band": joint,
                    "windows_samples": WINDOWS,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
