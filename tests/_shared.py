"""Helpers shared by several test files (each still checks against its own reference)."""

import contextlib
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, settings
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.datasets import euroc_v1_02_segment

SEG = euroc_v1_02_segment()
REPO = pathlib.Path(__file__).parent.parent
DATA = REPO / "tests" / "data"  # the test recordings (EuRoC and TUM-VI excerpts, bags)


def fast_settings(n, *checks):
    """Hypothesis settings of the suite: ``n`` examples, derandomised, no deadline and no
    example database (``checks``: further health checks to suppress)."""
    return settings(
        max_examples=n,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, *checks],
    )


def euroc_window(start_s, length_s):
    """Raw EuRoC samples of a window of the bundled V1_02 excerpt (its flight part) and the
    ground-truth biases at its start: ``(k0, gyro, accel, dt, bias)``."""
    k0 = int(round(start_s / 0.005))
    n = int(round(length_s / 0.005))
    dt = np.diff(SEG.t[k0 : k0 + n + 1])
    bias = jaximu.ImuBias(jnp.asarray(SEG.b_g_gt[k0]), jnp.asarray(SEG.b_a_gt[k0]))
    return k0, SEG.gyro[k0 : k0 + n], SEG.accel[k0 : k0 + n], dt, bias


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


def random_inputs(B, T, seed=0, big_angles=False, dtype=np.float64):
    """A random :class:`jaximu.NavState` batch ``(B,)`` (unit quaternions from scipy) and
    samples ``(B, T, 3)``: rates of 0.8 rad/s (``big_angles``: a third of the lanes turn by
    more than π/2 a step, the half angle's range-reduced branch), specific forces about
    gravity."""
    rng = np.random.default_rng(seed)
    q = Rotation.random(B, random_state=seed).as_quat(scalar_first=True)
    state = jaximu.NavState(
        *(
            jnp.asarray(x, dtype)
            for x in (
                q,
                rng.normal(size=(B, 3)),
                rng.normal(size=(B, 3)),
                0.01 * rng.normal(size=(B, 3)),
                0.1 * rng.normal(size=(B, 3)),
            )
        )
    )
    gyro = rng.normal(size=(B, T, 3)) * 0.8
    if big_angles:
        gyro[: B // 3] *= 400.0
    accel = rng.normal(size=(B, T, 3)) * 2 + [0, 0, 9.81]
    return state, jnp.asarray(gyro, dtype), jnp.asarray(accel, dtype)


@contextlib.contextmanager
def dispatch_as(backend):
    """Run the engine's dispatch as on ``backend`` (``"cpu"`` or ``"accelerator"``) whatever
    device runs it: the table's rows, the batch blocks, the stage conditionals
    (jaximu.kernels.device.backend, which the table re-exports as jaximu.engine._dispatch.backend).
    The jit caches are cleared around it: a traced entry does not key on the backend."""
    from jaximu.engine import _dispatch
    from jaximu.kernels import device

    saved = device.backend
    _dispatch.backend = device.backend = lambda: backend
    jax.clear_caches()
    try:
        yield
    finally:
        _dispatch.backend = device.backend = saved
        jax.clear_caches()
