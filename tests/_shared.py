"""Helpers shared by several test files (each still checks against its own reference)."""

import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu.datasets import euroc_v1_02_segment

SEG = euroc_v1_02_segment()


def euroc_window(start_s, length_s):
    """Raw EuRoC samples of a window of the bundled V1_02 excerpt (its flight part) and the
    ground-truth biases at its start: ``(k0, gyro, accel, dt, bias)``."""
    k0 = int(round(start_s / 0.005))
    n = int(round(length_s / 0.005))
    dt = np.diff(SEG.t[k0:k0 + n + 1])
    bias = jaximu.ImuBias(jnp.asarray(SEG.b_g_gt[k0]), jnp.asarray(SEG.b_a_gt[k0]))
    return k0, SEG.gyro[k0:k0 + n], SEG.accel[k0:k0 + n], dt, bias


def central_difference_phi(run, x0, eps=1e-6):
    """``Φ`` of ``run`` (a state -> state map) at ``x0`` by central differences through
    boxplus/boxminus: ``(15, 15)``."""
    nominal = run(x0)
    cols = []
    for i in range(15):
        d = np.zeros(15)
        d[i] = eps
        plus, minus = run(jaximu.boxplus(x0, d)), run(jaximu.boxplus(x0, -d))
        cols.append((jaximu.boxminus(plus, nominal) - jaximu.boxminus(minus, nominal)) / (2 * eps))
    return np.stack([np.asarray(c) for c in cols], axis=-1)
