"""A learned IMU correction trained end to end through jaximu's propagation.

A small MLP sees a causal window of raw samples and adds a correction to the current gyro
and accelerometer sample. It is trained on EuRoC V1_02 (the bundled 20 s excerpt) so that
1 s of dead reckoning from the true state ends where the ground truth does, with gradients
through :func:`jaximu.propagate_final`; it is evaluated on V2_01 (another room, another day),
which it never saw. Biases are not given to the integration: the network has to learn them.

    python examples/learned_correction.py [--steps 300] [--out learned_correction.png]
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from jaximu import NavState, datasets, learning  # noqa: E402


def recording(seg):
    """IMU samples with the ground truth at the IMU times (stamps coincide in EuRoC)."""
    idx = np.searchsorted(seg.t, seg.t_gt)
    ok = (idx < len(seg.t)) & (np.abs(seg.t[np.minimum(idx, len(seg.t) - 1)] - seg.t_gt) < 1e-6)
    i_imu, i_gt = idx[ok], np.nonzero(ok)[0]
    q = seg.q_gt[i_gt] / np.linalg.norm(seg.q_gt[i_gt], axis=-1, keepdims=True)  # |q| ≈ 1 ± 1e-4 in the file
    z = np.zeros((len(i_gt), 3))
    truth = NavState(jnp.asarray(q), jnp.asarray(seg.p_gt[i_gt]), jnp.asarray(seg.v_gt[i_gt]),
                     jnp.asarray(z), jnp.asarray(z))
    return seg.t[i_imu], seg.gyro[i_imu], seg.accel[i_imu], truth


def report(name, params, segs, window):
    rot, pos = learning.segment_errors(params, segs, window)
    r = np.degrees(np.linalg.norm(np.asarray(rot), axis=-1))
    p = np.linalg.norm(np.asarray(pos), axis=-1)
    print(f"  {name:<24} orientation error {np.sqrt(np.mean(r**2)):7.3f} deg RMS, "
          f"position error {100 * np.sqrt(np.mean(p**2)):7.2f} cm RMS")
    return r, p


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--window", type=int, default=16, help="samples the network sees")
    ap.add_argument("--length", type=int, default=200, help="steps per training piece")
    ap.add_argument("--out", default="learned_correction.png")
    args = ap.parse_args(argv)

    W, L = args.window, args.length
    t, g, a, truth = recording(datasets.euroc_v1_02_segment())
    train = learning.segments(t, g, a, truth, L, context=W, stride=L // 4)
    held_out = datasets.euroc_v2_01_segment()
    t, g, a, truth = recording(held_out)
    test = learning.segments(t, g, a, truth, L, context=W)
    # For context: the same pieces with the dataset's own bias estimates subtracted.
    debiased = test._replace(gyro=test.gyro - held_out.b_g_gt.mean(0),
                             accel=test.accel - held_out.b_a_gt.mean(0))
    print(f"train: EuRoC V1_02, {train.dt.shape[0]} pieces of {L} steps; "
          f"held out: EuRoC V2_01, {test.dt.shape[0]} pieces")

    params = learning.init_mlp(jax.random.key(0), [6 * W, 64, 64, 6])
    opt = optax.adam(optax.cosine_decay_schedule(3e-3, args.steps))
    state = opt.init(params)

    @jax.jit
    def step(params, state):
        loss, grad = jax.value_and_grad(learning.segment_loss)(params, train, W)
        updates, state = opt.update(grad, state, params)
        return optax.apply_updates(params, updates), state, loss

    t0 = time.perf_counter()
    params, state, loss0 = step(params, state)
    jax.block_until_ready(params)
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(1, args.steps):
        params, state, loss = step(params, state)
        if i % 100 == 0 or i == args.steps - 1:
            print(f"  step {i:4d}  training loss {float(loss):10.3f} (start {float(loss0):.3f})")
    jax.block_until_ready(params)
    print(f"training: {args.steps} steps in {time.perf_counter() - t0:.1f} s "
          f"(+ {t_compile:.1f} s compile and first step)")

    print("held-out sequence (EuRoC V2_01), 1 s dead reckoning from the true state:")
    r0, p0 = report("raw samples", None, test, W)
    r1, p1 = report("learned correction", params, test, W)
    report("dataset's biases removed", None, debiased, W)
    print("training sequence (EuRoC V1_02):")
    report("raw samples", None, train, W)
    report("learned correction", params, train, W)

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot (pip install 'jaximu[examples]')")
        return 0
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    x = np.arange(len(r0))
    for k, (before, after, unit, title) in enumerate(
            [(r0, r1, "deg", "orientation error after 1 s"),
             (100 * p0, 100 * p1, "cm", "position error after 1 s")]):
        ax[k].plot(x, before, "o-", label="raw samples")
        ax[k].plot(x, after, "o-", label="learned correction")
        ax[k].set(xlabel="piece of the held-out sequence (1 s each)", ylabel=unit, title=title)
        ax[k].legend()
    fig.suptitle("Learned IMU correction: trained on EuRoC V1_02, evaluated on V2_01")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
