"""Each batch block of a structure-of-arrays kernel is compiled by XLA:CPU as one kernel
(jaximu.kernels.soa.one_kernel, docs/DESIGN.md "One kernel per block"): the tag reaches the
compiled program, inputs that XLA can fold to constants (samples a user closes over) compile
and give the numbers of runtime inputs, and a block using an operation outside the emitter's
list runs as a plain call."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fast_path import inputs

import jaximu
from jaximu.kernels import soa as _soa

NOISE = jaximu.ImuNoise.euroc()
B, T = 4, 400  # each sample array 38 kB: above XLA:CPU's large-constant size


def _close(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * max(1.0, np.abs(y).max()))


def _runs(fn, *arrays):
    """``fn`` on runtime arguments and on the same values closed over as constants."""
    on_args = jax.jit(fn)(*arrays)
    const = [np.asarray(a) for a in arrays]
    closed = jax.jit(lambda: fn(*(jnp.asarray(c) for c in const)))()
    return on_args, closed


@pytest.mark.skipif(not _soa.ONE_KERNEL_ENABLED, reason="JAXIMU_ONE_KERNEL=0")
def test_the_tag_reaches_the_compiled_kernel():
    state, gyro, accel = inputs(B, T)
    P0 = jnp.broadcast_to(jnp.eye(15) * 1e-4, (B, 15, 15))
    hlo = (
        jax.jit(lambda s, w, a: jaximu.propagate_covariance_final(s, P0, w, a, 0.005, NOISE))
        .lower(state, gyro, accel)
        .compile()
        .as_text()
    )
    calls = [ln for ln in hlo.splitlines() if " call(" in ln and "xla_cpu_small_call" in ln]
    assert calls and all('inlineable="false"' in ln for ln in calls)


def test_constant_inputs_mean_and_every_state():
    state, gyro, accel = inputs(40, T // 4)  # 40 lanes: the structure-of-arrays rows
    for fn in (
        lambda w, a: jaximu.propagate_final(state, w, a, 0.005),
        lambda w, a: jaximu.propagate(state, w, a, 0.005),
    ):
        _close(*_runs(fn, gyro, accel))


def test_constant_inputs_covariance():
    state, gyro, accel = inputs(B, T)
    P0 = jnp.broadcast_to(jnp.eye(15) * 1e-4, (B, 15, 15))
    _close(
        *_runs(
            lambda w, a: jaximu.propagate_covariance_final(state, P0, w, a, 0.005, NOISE),
            gyro,
            accel,
        )
    )


def test_constant_inputs_preintegration():
    _, gyro, accel = inputs(B, T)
    for method in ("sequential", "parallel"):
        _close(
            *_runs(
                lambda w, a: jaximu.preintegrate(w, a, 0.005, None, NOISE, method=method),
                gyro,
                accel,
            )
        )
    _close(*_runs(lambda w, a: jaximu.preintegrate(w[0], a[0], 0.005, None, NOISE), gyro, accel))
    # blocks by jax.jvp inside the kernel. The sequential method: the autodiff blocks are
    # the same inside the kernel for both methods, and the parallel method's work on the
    # inputs outside it (padding, chunks as lanes) is checked above with constant inputs;
    # "auto" would pick the parallel one here, a program 1 s of CPU dearer per scheme.
    for scheme in ("euler", "midpoint"):
        _close(
            *_runs(
                lambda w, a: jaximu.preintegrate(
                    w, a, 0.005, None, NOISE, scheme, "sequential", jacobians="autodiff"
                ),
                gyro,
                accel,
            )
        )


def test_blocks_outside_the_emitter_list_run_as_plain_calls():
    x = jnp.ones((3, 3))
    safe = jax.make_jaxpr(
        lambda x: jax.lax.scan(lambda c, _: (c * 2.0 + 1.0, None), x, None, length=3)[0]
    )(x).jaxpr
    dot = jax.make_jaxpr(lambda x: jax.lax.cond(True, lambda y: y @ y, lambda y: y, x))(x)
    assert _soa._kernel_safe(safe)
    assert not _soa._kernel_safe(dot.jaxpr)  # a dot nested in a branch is found
    out = jax.jit(lambda x: _soa.one_kernel(lambda y: y @ y + 1.0, x))(x)
    np.testing.assert_allclose(out, np.full((3, 3), 4.0))


@pytest.mark.skipif(not _soa.ONE_KERNEL_ENABLED, reason="JAXIMU_ONE_KERNEL=0")
def test_derivatives_run_the_plain_call():
    """The tag is on the primal only. A tagged derivative kept neither guard of the primal:
    compiled as one function, an eager ``jax.grad`` of a 64 × 500 preintegration took LLVM
    150 s (10 s untagged), and samples closed over reached a tagged linear part as constants
    (the abort of ``test_constant_inputs_*``; see the linearize test below).

    The primal's tag is looked for in the compiled program; a derivative's in the program
    jaximu hands to XLA (the lowered module, before XLA's passes), where it would have to be
    to reach the compiled one: a stricter check (no tag at all, not only no tagged call),
    without compiling the eight derivatives."""
    state, gyro, accel = inputs(B, T // 4)

    def tagged_calls(fn):
        hlo = jax.jit(fn).lower(gyro).compile().as_text()
        return [
            ln
            for ln in hlo.splitlines()
            if "xla_cpu_small_call" in ln and 'inlineable="false"' in ln
        ]

    # losses that read the primal (a linear one needs only the residuals of its derivative)
    for loss in (
        lambda w: (jaximu.preintegrate(w, accel, 0.005, None, NOISE).delta_p ** 2).sum(),
        lambda w: (jaximu.propagate_final(state, w, accel, 0.005).p ** 2).sum(),
    ):
        assert tagged_calls(loss)
        # jax.linearize inside the jitted function: called eagerly it compiles its
        # primal-and-residuals program only to hand back the linear part (the largest
        # compile of this file). Traced, the lowered module holds that linear part and the
        # primal under linearize: no tag may appear in either.
        for derivative in (
            jax.grad(loss),
            jax.value_and_grad(loss),
            lambda w: jax.linearize(loss, w)[1](w),
            lambda w: jax.jvp(loss, (w,), (jnp.ones_like(w),)),
        ):
            assert "xla_cpu_small_call" not in jax.jit(derivative).lower(gyro).as_text()


def test_linearize_on_closed_over_samples():
    """``jax.linearize`` of the mean kernel with float32 samples closed over (constants of
    the linear function) aborted the process in XLA's emitter while derivatives were
    tagged. Its tangent against central differences of the float64 call."""
    d = np.random.default_rng(3).normal(size=(B, T // 8, 3)) * 1e-2

    def f(dtype):
        state, _, accel = inputs(B, T // 8, dtype=dtype)
        accel = np.asarray(accel)  # closed over: a constant
        return (lambda w: jaximu.propagate_final(state, w, accel, 0.005).p), inputs(
            B, T // 8, dtype=dtype
        )[1]

    f32, g32 = f(np.float32)
    _, f_lin = jax.linearize(f32, g32)
    tangent = f_lin(jnp.asarray(d, np.float32))
    f64, g64 = f(np.float64)
    eps = 1e-6
    fd = (f64(g64 + eps * d) - f64(g64 - eps * d)) / (2 * eps)
    np.testing.assert_allclose(tangent, fd, rtol=0, atol=1e-4 * np.abs(fd).max())
