"""A tour of jaximu on the bundled real EuRoC MAV excerpt.

    python examples/quickstart.py

1. propagate one second of real IMU data from the ground-truth state and compare;
2. the same with the 15×15 error-state covariance, and the 3σ position bound;
3. a batch of 64 trajectories with perturbed biases in one call;
4. preintegrate the same second between two keyframes, predict the second keyframe, and
   check the 15-dim residual against the ground truth, whitened by the covariance;
5. a gradient through the whole propagation (d final position / d gyro bias).
"""

import jax
import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu.datasets import euroc_v1_02_segment


def main():
    seg = euroc_v1_02_segment()
    k0, n = 1400, 200  # 7 s into the excerpt (in flight), 1 s at 200 Hz
    gyro, accel = seg.gyro[k0 : k0 + n], seg.accel[k0 : k0 + n]
    dt = np.diff(seg.t[k0 : k0 + n + 1])
    q0 = seg.q_gt[k0] / np.linalg.norm(seg.q_gt[k0])  # the file's |q| is off by ~1e-4
    state0 = jaximu.NavState(
        q=jnp.asarray(q0, jnp.float32),
        p=jnp.asarray(seg.p_gt[k0], jnp.float32),
        v=jnp.asarray(seg.v_gt[k0], jnp.float32),
        b_g=jnp.asarray(seg.b_g_gt[k0], jnp.float32),
        b_a=jnp.asarray(seg.b_a_gt[k0], jnp.float32),
    )
    gyro32, accel32, dt32 = (np.asarray(x, np.float32) for x in (gyro, accel, dt))

    # 1. mean propagation, every state
    states = jaximu.propagate(state0, gyro32, accel32, dt32, scheme="midpoint")
    err = np.linalg.norm(np.asarray(states.p[-1]) - seg.p_gt[k0 + n])
    print(f"1. after {dt.sum():.2f} s: position error {err:.3f} m against ground truth")

    # 2. with the covariance
    P0 = np.diag(np.r_[[1e-6] * 3, [1e-6] * 3, [1e-4] * 3, [1e-8] * 3, [1e-6] * 3]).astype(
        np.float32
    )
    final, P = jaximu.propagate_covariance_final(
        state0, P0, gyro32, accel32, dt32, jaximu.ImuNoise.euroc(), scheme="rk4"
    )
    sigma = np.sqrt(np.diag(np.asarray(P))[3:6])
    print(f"2. 3σ position bound after 1 s: {np.round(3 * sigma, 3)} m")

    # 3. 64 trajectories at once: biases perturbed by their uncertainty
    rng = np.random.default_rng(0)
    batch = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (64,) + x.shape), state0)
    batch = batch.replace(b_a=batch.b_a + jnp.asarray(rng.normal(size=(64, 3)) * 0.03, jnp.float32))
    finals = jaximu.propagate_final(batch, gyro32, accel32, dt32)
    spread = np.asarray(finals.p).std(axis=0)
    print(
        f"3. spread of 64 final positions for a 0.03 m/s² accel-bias spread: {np.round(spread, 4)} m"
    )

    # 4. preintegration between keyframes (float64 inputs run in float32 unless x64 is on)
    bias = jaximu.ImuBias(state0.b_g, state0.b_a)
    pim = jaximu.preintegrate(gyro32, accel32, dt32, bias, jaximu.ImuNoise.euroc())
    predicted = jaximu.predict(state0, pim)
    truth_j = state0.replace(
        q=jnp.asarray(seg.q_gt[k0 + n] / np.linalg.norm(seg.q_gt[k0 + n]), jnp.float32),
        p=jnp.asarray(seg.p_gt[k0 + n], jnp.float32),
        v=jnp.asarray(seg.v_gt[k0 + n], jnp.float32),
    )
    r = jaximu.residual(state0, truth_j, pim)
    print(
        f"4. preintegrated Δt = {float(pim.delta_t):.3f} s, predicted position off by "
        f"{np.linalg.norm(np.asarray(predicted.p - truth_j.p)):.3f} m; residual (θ, p, v) norms "
        f"{np.linalg.norm(np.asarray(r[:3])):.4f} rad, {np.linalg.norm(np.asarray(r[3:6])):.3f} m, "
        f"{np.linalg.norm(np.asarray(r[6:9])):.3f} m/s"
    )

    # 5. gradients through the propagation
    def final_x(b_g):
        return jaximu.propagate_final(state0.replace(b_g=b_g), gyro32, accel32, dt32).p[0]

    grad = jax.grad(final_x)(state0.b_g)
    print(f"5. ∂x_final/∂b_g = {np.round(np.asarray(grad), 3)} m per rad/s")


if __name__ == "__main__":
    main()
