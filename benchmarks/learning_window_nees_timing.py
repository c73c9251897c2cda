"""A reference timing noise in the windowed orientation NEES, fitted on a model's training
recordings and read on the one left out (a measurement in numpy/scipy over the library's
window terms; not a model setting).

    python benchmarks/learning_window_nees_timing.py MODEL SIGMA_M TAU TEST FIT_ON...

``MODEL``: a model trained without ``TEST``; ``SIGMA_M`` [rad/s], ``TAU`` [s]: its
Gauss–Markov gyro bias as fitted by ``benchmarks/learning_window_nees.py``; ``FIT_ON``: its
training recordings (sequence folders, as ``TEST``), whose validation parts (after 80 s)
the terms are fitted on, by the window likelihood (Nelder–Mead on the logarithms).

The term: the ground truth's attitude at each window end is taken at a time off by
``δ ~ N(0, σ_t²)`` [s] from the IMU's, so it is off by ``ω δ`` (body frame). Two forms:

* ``independent ends``: one ``δ`` per end, adding ``σ_t² (ΔRᵀ ω₀ ω₀ᵀ ΔR + ω₁ ω₁ᵀ)``;
* ``shared offset``: one ``δ`` per window (a slowly drifting clock offset), adding
  ``σ_t² v vᵀ``, ``v = ΔRᵀ ω₀ − ω₁``;

with ``ω₀``, ``ω₁`` the corrected gyro at the window's ends and ``ΔR`` the window's true
rotation. Each is fitted with the model's ``σ_m`` fixed and with ``σ_m`` fitted beside it, on
all of ``FIT_ON`` and on its Vicon-room recordings (``euroc_v*``) alone; last, the ``σ_t``
the left-out recording itself would want (in-sample, a bound on what the term can do).
"""

from __future__ import annotations

import pathlib
import sys

import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from jaximu import learning
from jaximu.learning import uncertainty as u


def rows(model, markov, folder, validation):
    """Per window length: errors ``r``, the model's covariance without the Gauss–Markov
    term ``base``, the unit Gauss–Markov term ``G`` and the two timing forms ``U``, ``V``."""
    s = learning.load_sequence(folder)
    k = len(s) - len(learning.split(s)[1]) if validation else 0
    parts = u._markov_parts(model, [s], [k], (1.0, 5.0))
    g = np.asarray(model(jnp.asarray(s.gyro, jnp.float32), jnp.asarray(s.accel, jnp.float32)).gyro)
    R = Rotation.from_quat(np.roll(np.asarray(s.q, np.float64), -1, axis=1))
    sb = float(model.bias_sigma)
    out = {}
    for w, found in parts.items():
        if not found:
            continue
        _, t, F, h = found[0]
        n = int(round(w * s.rate_hz))
        i0 = k + n * np.arange((len(s) - 1 - k) // n)
        i0 = i0[s.has_reference[i0] & s.has_reference[i0 + n]]
        G = np.asarray(u._with_markov_terms(t, F, h, markov).W - t.W, np.float64) / markov[0] ** 2
        W, B = np.asarray(t.W, np.float64), np.asarray(t.B, np.float64)
        a = np.einsum("kji,kj->ki", (R[i0].inv() * R[i0 + n]).as_matrix(), g[i0])
        b = g[i0 + n]
        outer = lambda x: np.einsum("ki,kj->kij", x, x)  # noqa: E731
        base = W + sb**2 * B @ B.transpose(0, 2, 1) + 2 * float(t.reference_sigma) ** 2 * np.eye(3)
        out[w] = dict(
            r=np.asarray(t.r, np.float64), base=base, G=G, U=outer(a) + outer(b), V=outer(a - b)
        )
    return out


def covariance(d, sm, st, form):
    return d["base"] + sm**2 * d["G"] + st**2 * d[form]


def quadratic(r, S):
    """``rᵀ S⁻¹ r`` per window, ``r`` ``(K, 3)``, ``S`` ``(K, 3, 3)``."""
    return np.einsum("ki,ki->k", r, np.linalg.solve(S, r[..., None])[..., 0])


def nees(d, sm, st, form):
    return float(np.mean(quadratic(d["r"], covariance(d, sm, st, form))))


def nll(p, data, form, fixed_sm):
    sm = np.exp(p[0]) if fixed_sm is None else fixed_sm
    out = 0.0
    for w in (1.0, 5.0):
        r = np.concatenate([d[w]["r"] for d in data if w in d])
        S = np.concatenate([covariance(d[w], sm, np.exp(p[-1]), form) for d in data if w in d])
        out += np.mean(0.5 * quadratic(r, S) + 0.5 * np.linalg.slogdet(S)[1])
    return out


def main():
    path, sm0, tau, test, *fit_on = sys.argv[1:]
    model = learning.load(path)
    markov = (float(sm0), float(tau))
    train = {n: rows(model, markov, n, True) for n in fit_on}
    te = rows(model, markov, test, False)
    line = lambda d, sm, st, f: " ".join(  # noqa: E731
        f"{w:g}s {nees(d[w], markov[0], 0.0, f):.2f}->{nees(d[w], sm, st, f):.2f}" for w in d
    )
    vicon = [n for n in fit_on if pathlib.Path(n).name.startswith("euroc_v")]
    for form, subset in (("U", fit_on), ("U", vicon), ("V", vicon)):
        data = [train[n] for n in subset]
        print(f"=== {'independent ends' if form == 'U' else 'shared offset'}, fitted on {subset}")
        for label, fixed in (("σ_m fixed", markov[0]), ("σ_m refitted", None)):
            p0 = [np.log(1e-3)] if fixed is not None else [np.log(markov[0]), np.log(1e-3)]
            p = minimize(nll, p0, args=(data, form, fixed), method="Nelder-Mead").x
            sm, st = (fixed if fixed is not None else float(np.exp(p[0]))), float(np.exp(p[-1]))
            print(f"{label}: σ_m {sm:.3g} rad/s, σ_t {st * 1e3:.3g} ms")
            for n, d in zip(subset, data):
                print(f"   val {n}: {line(d, sm, st, form)}")
            print(f"   TEST {test}: {line(te, sm, st, form)}")
    p = minimize(nll, [np.log(1e-3)], args=([te], "U", markov[0]), method="Nelder-Mead").x
    st = float(np.exp(p[0]))
    print(
        f"in-sample on {test} (independent ends, σ_m fixed): σ_t {st * 1e3:.3g} ms: {line(te, markov[0], st, 'U')}"
    )


if __name__ == "__main__":
    main()
