"""Tests for ``jaximu.so3``.

Every check compares the library against something independent of it:

* ``scipy.spatial.transform.Rotation`` (converted through scipy's ``[x, y, z, w]`` order by
  hand, so no ``scalar_first`` is needed);
* plain-numpy transcriptions of published formulas written below (Hamilton product in
  scalar/vector form, the JPL matrix ``C(q̄)`` of Trawny & Roumeliotis TR 2005-002,
  the right Jacobian as its power series ``Jr(φ) = Σ_k (-[φ]x)^k / (k+1)!``);
* central finite differences (of scipy's maps, or of the function whose autodiff gradient
  is checked);
* closed-form identities (``d Exp/dφ`` at 0, ``Log ∘ Exp = id``, ...).

Tolerances, unless a test says otherwise:

* ``TOL64 = 1e-13``: float64 values of unit-size quantities computed by short closed forms
  (~450 ulps of eps64 ≈ 2.2e-16; observed errors are <= 1e-15: rounding of the trigonometric
  evaluations, and the ~1e-11 relative loss of the closed forms just above the Taylor switch
  only affects coefficients multiplied by θ² ≈ 1e-4).
* ``TOL32 = 1e-6``: float32 values of unit-size quantities, ≈ 8 ulps at 1.0 (eps32 ≈ 1.19e-7),
  scaled by ``max(1, |reference|)`` where the output can reach π.
"""

from __future__ import annotations

import functools
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaximu import so3

# Compiling is the dominant cost of this file (eager dispatch compiles every primitive
# separately; XLA:CPU's default pipeline spends seconds on the autodiff graphs). So library
# calls go through `fast_jit`: one compile per input shape/dtype, with XLA options that cut
# compile time several-fold. They change code generation, not the arithmetic performed; if a
# backend rejects them we fall back to the defaults.
_FAST_COMPILE = {
    "xla_backend_optimization_level": 0,
    "xla_cpu_use_fusion_emitters": False,
    "xla_llvm_disable_expensive_passes": True,
}


def fast_jit(fn):
    jitted = jax.jit(fn)
    cache = {}

    @functools.wraps(fn)
    def call(*args):
        args = jax.tree.map(jnp.asarray, args)
        leaves, treedef = jax.tree.flatten(args)
        key = (treedef, tuple((a.shape, a.dtype) for a in leaves))
        if key not in cache:
            lowered = jitted.lower(*args)
            try:
                cache[key] = lowered.compile(compiler_options=_FAST_COMPILE)
            except Exception:  # pragma: no cover - backend without these options
                cache[key] = lowered.compile()
        return cache[key](*args)

    return call


# Library functions, compiled (no quat_identity: its arguments are static).
J = types.SimpleNamespace(
    **{name: fast_jit(getattr(so3, name)) for name in so3.__all__ if name != "quat_identity"}
)

PI = np.pi
TOL64 = 1e-13
TOL32 = 1e-6

# Squared-angle Taylor switch points of the library (documented in ``_taylor_threshold``).
SWITCH64 = 1e-4
SWITCH32 = 4e-3

AXES = np.array(
    [
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 2.0, 3.0],
        [-0.3, 0.5, -0.8],
        [1.0, 1.0, 0.0],
        [1.0, 1.0, 1.0],
    ]
)
AXES = AXES / np.linalg.norm(AXES, axis=-1, keepdims=True)

# Edge-case angles (radians) used throughout; all <= pi.
EDGE_ANGLES = {
    "zero": 0.0,
    "1e-8": 1e-8,
    "1e-4": 1e-4,
    "f64_switch_below": np.sqrt(SWITCH64 * (1 - 1e-3)),
    "f64_switch_above": np.sqrt(SWITCH64 * (1 + 1e-3)),
    "f32_switch_below": np.sqrt(SWITCH32 * (1 - 1e-3)),
    "f32_switch_above": np.sqrt(SWITCH32 * (1 + 1e-3)),
    "1": 1.0,
    "3": 3.0,
    "pi-1e-3": PI - 1e-3,
    "pi-1e-6": PI - 1e-6,
    "pi": PI,
}


# --------------------------------------------------------------------------- references


def np_skew(v):
    v = np.asarray(v, dtype=np.float64)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2
    )


def np_qmul(p, q):
    """Hamilton product in scalar/vector form: (a, u)(b, v) = (ab - u·v, a v + b u + u × v)."""
    p, q = np.broadcast_arrays(np.asarray(p, np.float64), np.asarray(q, np.float64))
    a, u = p[..., :1], p[..., 1:]
    b, v = q[..., :1], q[..., 1:]
    w = a * b - np.sum(u * v, axis=-1, keepdims=True)
    return np.concatenate([w, a * v + b * u + np.cross(u, v)], axis=-1)


def sp_rot(q_wxyz):
    """scipy Rotation of a Hamilton [w, x, y, z] quaternion (reordered by hand)."""
    q = np.asarray(q_wxyz, np.float64)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def sp_quat(rot, canonical=True):
    """[w, x, y, z] of a scipy Rotation; canonical: w >= 0."""
    q = rot.as_quat()[..., [3, 0, 1, 2]]
    if canonical:
        q = np.where(q[..., :1] < 0, -q, q)
    return q


def np_exp_quat(phi):
    """[cos(θ/2), sin(θ/2) φ/θ] through scipy (angle-axis, independent of the library)."""
    return sp_quat(Rotation.from_rotvec(np.asarray(phi, np.float64)), canonical=False)


def np_jr_series(phi, terms=60):
    """Right Jacobian as its defining power series Σ_k (-[φ]x)^k / (k+1)! (all φ)."""
    mK = -np_skew(phi)
    term = np.broadcast_to(np.eye(3), mK.shape).copy()
    acc = term.copy()
    for k in range(1, terms):
        term = term @ mK / (k + 1)
        acc = acc + term
    return acc


def np_jpl_C(qbar):
    """JPL C(q̄) = (2 q4² - 1) I - 2 q4 [q×] + 2 q qᵀ, q̄ = [q1, q2, q3, q4].

    Trawny & Roumeliotis, "Indirect Kalman Filter for 3D Attitude Estimation", TR 2005-002.
    """
    qbar = np.asarray(qbar, np.float64)
    q, q4 = qbar[..., :3], qbar[..., 3]
    eye = np.eye(3)
    return (
        (2 * q4**2 - 1)[..., None, None] * eye
        - 2 * q4[..., None, None] * np_skew(q)
        + 2 * q[..., :, None] * q[..., None, :]
    )


def assert_quat_close(a, b, atol):
    """Equal up to the sign ambiguity q ~ -q, per sample."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    err = np.minimum(np.abs(a - b).max(-1), np.abs(a + b).max(-1))
    assert np.all(err <= atol), f"max err {err.max():.3e} > {atol:.1e}"


def assert_rotvec_close(a, b, atol):
    """Rotation vectors equal, or both of angle ~π and equal up to sign (axis·π ~ -axis·π)."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    err = np.abs(a - b).max(-1)
    near_pi = np.linalg.norm(b, axis=-1) > PI - 1e-5
    err = np.where(near_pi, np.minimum(err, np.abs(a + b).max(-1)), err)
    assert np.all(err <= atol), f"max err {err.max():.3e} > {atol:.1e}"


def random_unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def random_rotvecs(rng, n, max_angle=PI):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=(n, 1))


def edge_rotvecs(angles=None):
    """All edge angles about all AXES, shape (n_angles * n_axes, 3)."""
    angles = np.array(list(EDGE_ANGLES.values()) if angles is None else angles)
    return (angles[:, None, None] * AXES[None]).reshape(-1, 3)


N = 200


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# --------------------------------------------------------------------------- test helpers


def test_reference_jpl_formula_sanity():
    # Transcription check of np_jpl_C: a JPL rotation about z by θ is the *frame* rotation
    # C = Rz(θ)ᵀ = [[c, s, 0], [-s, c, 0], [0, 0, 1]] (TR 2005-002, Sec. 2.2).
    th = 0.7
    qbar = np.array([0, 0, np.sin(th / 2), np.cos(th / 2)])
    c, s = np.cos(th), np.sin(th)
    np.testing.assert_allclose(np_jpl_C(qbar), [[c, s, 0], [-s, c, 0], [0, 0, 1]], atol=1e-15)


def test_reference_jr_series_sanity():
    # The series reference equals the textbook closed form at a generic angle.
    phi = np.array([0.4, -1.1, 0.7])
    th = np.linalg.norm(phi)
    K = np_skew(phi)
    closed = np.eye(3) - (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K
    np.testing.assert_allclose(np_jr_series(phi), closed, atol=1e-15)


# --------------------------------------------------------------------------- 1. vs scipy


def test_quat_mul_vs_scipy_and_formula(rng):
    p, q = random_unit_quats(rng, N), random_unit_quats(rng, N)
    out = np.asarray(J.quat_mul(jnp.asarray(p), jnp.asarray(q)))
    # Exact (sign included) against the scalar/vector form of the Hamilton product.
    np.testing.assert_allclose(out, np_qmul(p, q), atol=TOL64)
    # R(p ⊗ q) = R(p) R(q) as rotations (scipy's `*` composes like matrix products).
    assert_quat_close(out, sp_quat(sp_rot(p) * sp_rot(q)), TOL64)


def test_quat_conj_vs_scipy(rng):
    q = random_unit_quats(rng, N)
    out = np.asarray(J.quat_conj(jnp.asarray(q)))
    np.testing.assert_allclose(out[:, 0], q[:, 0], atol=0)
    np.testing.assert_allclose(out[:, 1:], -q[:, 1:], atol=0)
    np.testing.assert_allclose(sp_rot(out).as_matrix(), sp_rot(q).inv().as_matrix(), atol=TOL64)


def test_quat_rotate_vs_scipy(rng):
    q = random_unit_quats(rng, N)
    v = rng.normal(size=(N, 3))
    out = J.quat_rotate(jnp.asarray(q), jnp.asarray(v))
    np.testing.assert_allclose(out, sp_rot(q).apply(v), atol=TOL64)


def test_quat_to_matrix_vs_scipy(rng):
    q = random_unit_quats(rng, N)
    np.testing.assert_allclose(J.quat_to_matrix(jnp.asarray(q)), sp_rot(q).as_matrix(), atol=TOL64)


def test_matrix_to_quat_vs_scipy(rng):
    q = random_unit_quats(rng, N)
    R = sp_rot(q).as_matrix()
    out = np.asarray(J.matrix_to_quat(jnp.asarray(R)))
    assert np.all(out[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=TOL64)
    # w >= 0 and q is unique up to sign: compare with scipy up to sign, and with the
    # canonical (w >= 0) form of the quaternion the matrix was built from.
    assert_quat_close(out, sp_quat(Rotation.from_matrix(R)), TOL64)
    np.testing.assert_allclose(out, np.where(q[:, :1] < 0, -q, q), atol=TOL64)


def test_matrix_to_quat_all_shepperd_branches(rng):
    # Random rotations hit every branch: check each branch is represented and correct.
    q = random_unit_quats(rng, N)
    R = sp_rot(q).as_matrix()
    d = np.stack(
        [
            1 + np.trace(R, axis1=-2, axis2=-1),
            1 + R[:, 0, 0] - R[:, 1, 1] - R[:, 2, 2],
            1 - R[:, 0, 0] + R[:, 1, 1] - R[:, 2, 2],
            1 - R[:, 0, 0] - R[:, 1, 1] + R[:, 2, 2],
        ],
        -1,
    )
    branch = np.argmax(d, -1)
    assert set(branch.tolist()) == {0, 1, 2, 3}
    out = np.asarray(J.matrix_to_quat(jnp.asarray(R)))
    for b in range(4):
        sel = branch == b
        assert_quat_close(out[sel], q[sel], TOL64)


@pytest.mark.parametrize(
    "axis",
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 1, 1], [1, -2, 3]],
    ids=["x", "y", "z", "xy", "yz", "xyz", "generic"],
)
@pytest.mark.parametrize("angle", [PI, PI - 1e-6, PI - 1e-3], ids=["pi", "pi-1e-6", "pi-1e-3"])
def test_matrix_to_quat_half_turns(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    R = Rotation.from_rotvec(angle * axis).as_matrix()
    out = np.asarray(J.matrix_to_quat(jnp.asarray(R)))
    expected = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    assert_quat_close(out, expected, TOL64)
    assert out[0] >= 0
    assert_rotvec_close(np.asarray(J.log_matrix(jnp.asarray(R))), angle * axis, TOL64)


def test_matrix_to_quat_exact_half_turn_matrices():
    # 180° about x / y / z: R = diag with two -1's; these are the pure Shepperd x/y/z branches.
    for i in range(3):
        R = -np.eye(3)
        R[i, i] = 1.0
        expected = np.zeros(4)
        expected[1 + i] = 1.0
        out = np.asarray(J.matrix_to_quat(jnp.asarray(R)))
        assert_quat_close(out, expected, 0)
        assert_rotvec_close(np.asarray(J.log_matrix(jnp.asarray(R))), PI * expected[1:], 1e-15)


def test_exp_vs_scipy_random(rng):
    phi = random_rotvecs(rng, N)
    out = np.asarray(J.exp(jnp.asarray(phi)))
    np.testing.assert_allclose(out, sp_quat(Rotation.from_rotvec(phi)), atol=TOL64)
    np.testing.assert_allclose(
        J.exp_matrix(jnp.asarray(phi)), Rotation.from_rotvec(phi).as_matrix(), atol=TOL64
    )


def test_exp_vs_scipy_edges_and_beyond_pi():
    phi = np.concatenate([edge_rotvecs(), edge_rotvecs([4.0, 2 * PI - 1e-3, 2 * PI, 7.0])])
    out = np.asarray(J.exp(jnp.asarray(phi)))
    # Closed form (w = cos(θ/2), sign included), and scipy up to sign.
    th = np.linalg.norm(phi, axis=-1)
    np.testing.assert_allclose(out[:, 0], np.cos(th / 2), atol=TOL64)
    assert_quat_close(out, sp_quat(Rotation.from_rotvec(phi)), TOL64)
    np.testing.assert_allclose(
        J.exp_matrix(jnp.asarray(phi)), Rotation.from_rotvec(phi).as_matrix(), atol=TOL64
    )


def test_log_vs_scipy_random(rng):
    q = random_unit_quats(rng, N)  # about half have w < 0
    assert np.any(q[:, 0] < 0) and np.any(q[:, 0] > 0)
    out = np.asarray(J.log(jnp.asarray(q)))
    np.testing.assert_allclose(out, sp_rot(q).as_rotvec(), atol=TOL64)
    # q and -q give the same result.
    np.testing.assert_allclose(J.log(jnp.asarray(-q)), out, atol=TOL64)
    R = sp_rot(q).as_matrix()
    np.testing.assert_allclose(J.log_matrix(jnp.asarray(R)), sp_rot(q).as_rotvec(), atol=TOL64)


def test_log_vs_scipy_edges():
    phi = edge_rotvecs()
    q = np_exp_quat(phi)
    expected = Rotation.from_rotvec(phi).as_rotvec()
    for qq in (q, -q):  # -q has w < 0 (or w ~ -0 at pi)
        assert_rotvec_close(np.asarray(J.log(jnp.asarray(qq))), expected, TOL64)
    R = Rotation.from_rotvec(phi).as_matrix()
    assert_rotvec_close(np.asarray(J.log_matrix(jnp.asarray(R))), expected, TOL64)
    # Angles strictly below pi must come back with their sign (no ambiguity there).
    th = np.linalg.norm(phi, axis=-1)
    below = th < PI - 1e-7
    np.testing.assert_allclose(np.asarray(J.log(jnp.asarray(-q)))[below], phi[below], atol=TOL64)


def test_log_at_pi_sign_ambiguity():
    for axis in AXES:
        q = np.concatenate([[0.0], axis])
        for qq in (q, -q):
            out = np.asarray(J.log(jnp.asarray(qq)))
            np.testing.assert_allclose(np.linalg.norm(out), PI, atol=TOL64)
            assert_rotvec_close(out, PI * axis, TOL64)


# --------------------------------------------------------------------------- 2. round trips


def test_log_exp_round_trip(rng):
    phi = np.concatenate(
        [random_rotvecs(rng, N, max_angle=PI - 1e-6), edge_rotvecs()[: -len(AXES)]]
    )
    assert np.linalg.norm(phi, axis=-1).max() < PI
    np.testing.assert_allclose(J.log(J.exp(jnp.asarray(phi))), phi, atol=TOL64)
    np.testing.assert_allclose(J.log_matrix(J.exp_matrix(jnp.asarray(phi))), phi, atol=TOL64)


def test_exp_log_round_trip(rng):
    q = random_unit_quats(rng, N)
    back = np.asarray(J.exp(J.log(jnp.asarray(q))))
    assert_quat_close(back, q, TOL64)
    R = sp_rot(q).as_matrix()
    np.testing.assert_allclose(J.exp_matrix(J.log_matrix(jnp.asarray(R))), R, atol=TOL64)


# --------------------------------------------------------------------------- 3. Jacobians

# Central differences in float64 with step H: truncation ~H²·|f'''| ≈ 1e-12, rounding
# ~eps64/H ≈ 1e-10, so FD agrees with the true Jacobian to ~1e-9 absolute on O(1) entries.
H = 1e-6
FD_ATOL = 1e-8
FD_RTOL = 1e-7


def fd_jacobian(f, x, h=H):
    """Central-difference Jacobian of a batched numpy map f: (n, d) -> (n, m); returns (n, m, d)."""
    x = np.asarray(x, np.float64)
    cols = []
    for j in range(x.shape[-1]):
        e = np.zeros(x.shape[-1])
        e[j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, -1)


def _jacobian_points(rng):
    return np.concatenate(
        [
            random_rotvecs(rng, 50, max_angle=3.0),
            1e-8 * AXES,
            3.0 * AXES,
            (PI - 1e-3) * AXES,
        ]
    )


def test_right_jacobian_vs_series(rng):
    phi = np.concatenate([_jacobian_points(rng), edge_rotvecs()])
    np.testing.assert_allclose(J.right_jacobian(jnp.asarray(phi)), np_jr_series(phi), atol=TOL64)


def test_right_jacobian_vs_finite_differences(rng):
    # Exp(φ + δ) = Exp(φ) Exp(Jr(φ) δ + O(δ²))  =>  Jr = ∂/∂δ Log(Exp(φ)ᵀ Exp(φ + δ))
    # at δ = 0, evaluated with scipy.
    phi = _jacobian_points(rng)
    R0 = Rotation.from_rotvec(phi)
    fd = fd_jacobian(lambda p: (R0.inv() * Rotation.from_rotvec(p)).as_rotvec(), phi)
    np.testing.assert_allclose(J.right_jacobian(jnp.asarray(phi)), fd, atol=FD_ATOL, rtol=FD_RTOL)


def test_left_jacobian_is_transpose_and_vs_fd(rng):
    phi = _jacobian_points(rng)
    Jl = np.asarray(J.left_jacobian(jnp.asarray(phi)))
    np.testing.assert_allclose(Jl, np.swapaxes(np_jr_series(phi), -1, -2), atol=TOL64)
    # Exp(φ + δ) = Exp(Jl(φ) δ) Exp(φ)  =>  Jl = ∂/∂δ Log(Exp(φ + δ) Exp(φ)ᵀ).
    R0 = Rotation.from_rotvec(phi)
    fd = fd_jacobian(lambda p: (Rotation.from_rotvec(p) * R0.inv()).as_rotvec(), phi)
    np.testing.assert_allclose(Jl, fd, atol=FD_ATOL, rtol=FD_RTOL)


def test_right_jacobian_inv(rng):
    phi = _jacobian_points(rng)
    Jinv = np.asarray(J.right_jacobian_inv(jnp.asarray(phi)))
    # Inverse of the (series) right Jacobian.
    np.testing.assert_allclose(Jinv, np.linalg.inv(np_jr_series(phi)), atol=TOL64)
    Jr = np.asarray(J.right_jacobian(jnp.asarray(phi)))
    np.testing.assert_allclose(Jr @ Jinv, np.broadcast_to(np.eye(3), Jinv.shape), atol=TOL64)
    # Log(Exp(φ) Exp(δ)) = φ + Jr⁻¹(φ) δ + O(δ²): FD in δ at 0 with scipy.
    R0 = Rotation.from_rotvec(phi)
    fd = fd_jacobian(lambda d: (R0 * Rotation.from_rotvec(d)).as_rotvec(), np.zeros_like(phi))
    np.testing.assert_allclose(Jinv, fd, atol=FD_ATOL, rtol=FD_RTOL)


def test_gtsam_anchor_bias_derivative():
    # GTSAM testRot3 / preintegration: ∂Exp((ω - b) dt)/∂b = -Jr((ω - b) dt) dt (right
    # perturbation), checked by FD on the rotation: Log(Exp(θ(0))ᵀ Exp(θ(δ))) / δ.
    omega, dt = np.array([0.1, 0.0, 0.0]), 0.5
    R0 = Rotation.from_rotvec(omega * dt)
    fd = fd_jacobian(
        lambda b: (R0.inv() * Rotation.from_rotvec((omega - b) * dt)).as_rotvec(), np.zeros((1, 3))
    )[0]
    expected = -np.asarray(J.right_jacobian(jnp.asarray(omega * dt))) * dt
    np.testing.assert_allclose(expected, fd, atol=FD_ATOL, rtol=FD_RTOL)


def test_gtsam_anchor_logmap_derivative():
    # ∂Log(Exp(θ̂) Exp(δ))/∂δ at 0 = Jr⁻¹(θ̂), θ̂ = (0.1, 0.1, 0) (GTSAM LogmapDerivative).
    th = np.array([0.1, 0.1, 0.0])
    R0 = Rotation.from_rotvec(th)
    fd = fd_jacobian(lambda d: (R0 * Rotation.from_rotvec(d)).as_rotvec(), np.zeros((1, 3)))[0]
    np.testing.assert_allclose(
        J.right_jacobian_inv(jnp.asarray(th)), fd, atol=FD_ATOL, rtol=FD_RTOL
    )


def test_autodiff_of_log_exp_composition_matches_jr_inv(rng):
    # The autodiff Jacobian of Log(Exp(φ) Exp(δ)) in δ at 0 (a different code path through
    # exp, quat_mul and log) equals the closed-form Jr⁻¹.
    phi = _jacobian_points(rng)

    def jac(p):
        return jax.jacfwd(lambda d: so3.log(so3.quat_mul(so3.exp(p), so3.exp(d))))(jnp.zeros(3))

    out = fast_jit(jax.vmap(jac))(jnp.asarray(phi))
    # Exact derivative of a composition of closed forms: agreement to rounding (float64).
    np.testing.assert_allclose(out, np.linalg.inv(np_jr_series(phi)), atol=TOL64)


# --------------------------------------------------------------------------- 4. gradients

# φ = 0, tiny (1e-8; 1e-10, where θ⁴ ≈ 1e-40 underflows in float32), small (Taylor branch in
# both dtypes) and near π, all about one generic axis.
GRAD_ANGLES = {"0": 0.0, "1e-10": 1e-10, "1e-8": 1e-8, "1e-3": 1e-3, "pi-1e-3": PI - 1e-3}
GRAD_AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
_w = np.random.default_rng(777)
C3 = _w.normal(size=3)
C4 = _w.normal(size=4)
C33 = _w.normal(size=(3, 3))
Q0 = random_unit_quats(_w, 1)[0]
E3 = np.eye(3)


def _c(c, x):
    """Weights in the dtype of x (so float32 stays float32 under x64)."""
    return jnp.asarray(c, x.dtype)


def _phis():
    return np.array(list(GRAD_ANGLES.values()))[:, None] * GRAD_AXIS


def _qmul_pure(q, v):
    return np_qmul(q, np.concatenate([[0.0], v]))


# name -> (scalar f of a flat vector, inputs (n_angles, d) in float64, analytic gradient at
# angle 0 or None, gradient valid at *every* angle (closed-form identity) or None).
GRAD_CASES = {
    "exp": (
        lambda x: jnp.dot(so3.exp(x), _c(C4, x)),
        _phis,
        lambda: 0.5 * C4[1:],  # d exp/dφ at 0 = [0; ½ I]
        None,
    ),
    "exp_matrix": (
        lambda x: jnp.sum(so3.exp_matrix(x) * _c(C33, x)),
        _phis,
        lambda: np.array([np.sum(C33 * np_skew(e)) for e in E3]),  # dR/dφ_i at 0 = [e_i]x
        None,
    ),
    "log": (
        lambda x: jnp.dot(so3.log(x), _c(C3, x)),
        lambda: np_exp_quat(_phis()),
        lambda: np.concatenate([[0.0], 2 * C3]),  # log(w, u) ≈ 2u near identity
        None,
    ),
    "log_matrix": (
        lambda x: jnp.dot(so3.log_matrix(x.reshape(x.shape[:-1] + (3, 3))), _c(C3, x)),
        lambda: Rotation.from_rotvec(_phis()).as_matrix().reshape(-1, 9),
        lambda: (0.5 * np_skew(C3)).ravel(),  # log_matrix(R) ≈ vee((R - Rᵀ)/2) near I
        None,
    ),
    "right_jacobian": (
        lambda x: jnp.sum(so3.right_jacobian(x) * _c(C33, x)),
        _phis,
        lambda: np.array([-0.5 * np.sum(C33 * np_skew(e)) for e in E3]),  # Jr ≈ I - ½[φ]x
        None,
    ),
    "right_jacobian_inv": (
        lambda x: jnp.sum(so3.right_jacobian_inv(x) * _c(C33, x)),
        _phis,
        lambda: np.array([0.5 * np.sum(C33 * np_skew(e)) for e in E3]),  # Jr⁻¹ ≈ I + ½[φ]x
        None,
    ),
    "quat_first_order_update": (
        lambda x: jnp.dot(so3.quat_first_order_update(x[..., :4], x[..., 4:]), _c(C4, x)),
        lambda: np.concatenate([np.broadcast_to(Q0, (len(GRAD_ANGLES), 4)), _phis()], -1),
        # At φ = 0: d/dq normalize(q) = I - q qᵀ; d/dφ_i = ½ q ⊗ [0, e_i].
        lambda: np.concatenate(
            [(np.eye(4) - np.outer(Q0, Q0)) @ C4, [C4 @ (0.5 * _qmul_pure(Q0, e)) for e in E3]]
        ),
        None,
    ),
    "log_of_exp": (
        lambda x: jnp.dot(so3.log(so3.exp(x)), _c(C3, x)),
        _phis,
        None,
        lambda: C3,  # Log(Exp(φ)) = φ for |φ| < π
    ),
    "log_matrix_of_exp_matrix": (
        lambda x: jnp.dot(so3.log_matrix(so3.exp_matrix(x)), _c(C3, x)),
        _phis,
        None,
        lambda: C3,
    ),
}

GRAD_MODES = {"grad": jax.grad, "jacfwd": jax.jacfwd, "jacrev": jax.jacrev}


def _bundle(xs, pts):
    """All cases x all modes, plus the function values at the FD points, in one function."""
    grads = {
        c: {m: jax.vmap(GRAD_MODES[m](GRAD_CASES[c][0]))(x) for m in GRAD_MODES}
        for c, x in xs.items()
    }
    values = {c: jax.vmap(GRAD_CASES[c][0])(p) for c, p in pts.items()}
    return grads, values


def _grad_inputs():
    """Inputs per case (n_angles, d) and central-FD points (n_angles * 2 * d, d), float64."""
    xs, pts = {}, {}
    for c, v in GRAD_CASES.items():
        x = np.asarray(v[1](), np.float64)
        n, d = x.shape
        e = H * np.eye(d)
        xs[c] = x
        pts[c] = np.concatenate([x[:, None] + e, x[:, None] - e], 1).reshape(-1, d)
    return xs, pts


# One compile per dtype for every case and mode.
_compiled_bundle = fast_jit(_bundle)


@functools.cache
def _grads(which):
    """which: "f64", "f32", or "f64@f32" (float64 gradients at the float32-rounded inputs).

    Returns (gradients {case: {mode: (n_angles, d)}}, central FD gradients {case: (n, d)}).
    """
    dtype = jnp.float32 if which == "f32" else jnp.float64
    xs, pts = _grad_inputs()
    if which == "f64@f32":
        xs = jax.tree.map(lambda a: a.astype(np.float32).astype(np.float64), xs)
    if which == "f32":
        pts = {}  # no finite differences in float32
    args = jax.tree.map(lambda a: jnp.asarray(a, dtype), (xs, pts))
    grads, values = jax.tree.map(np.asarray, _compiled_bundle(*args))
    fd = {}
    for c in values:
        n, d = xs[c].shape
        v = values[c].reshape(n, 2, d)
        fd[c] = (v[:, 0] - v[:, 1]) / (2 * H)
    return grads, fd


# float32 gradients vs float64 gradients at the same (float32-rounded) point: 1e-5 relative
# to max(1, |g|), i.e. ~80 float32 ulps. Loose on purpose: the gradient graphs chain ~10-20
# rounded operations whose rounding is platform dependent; observed errors are <= 2.3e-7
# (~2 ulps), so a real loss of accuracy (e.g. a cancellation in a closed form) still shows.
GRAD32_TOL = 1e-5

# Regression guard: the closed forms of Jr and Jr⁻¹ once divided by the raw θ², which made
# grad/jacrev NaN at |φ| = 0 (and |φ| <= 3e-10 in float32) through the unused branch.


def _grad_params(dtype):
    out = []
    for c in GRAD_CASES:
        for a in GRAD_ANGLES:
            out.append(pytest.param(c, a, id=f"{c}-{a}"))
    return out


@pytest.mark.parametrize("case,angle", _grad_params("f64"))
def test_gradients_float64(case, angle):
    i = list(GRAD_ANGLES).index(angle)
    _, _, analytic0, identity = GRAD_CASES[case]
    grads, fd = _grads("f64")
    fd = fd[case][i]
    for mode, g in grads[case].items():
        g = g[i]
        assert g.dtype == np.float64
        assert np.all(np.isfinite(g)), (mode, g)
        np.testing.assert_allclose(g, fd, atol=FD_ATOL, rtol=FD_RTOL, err_msg=mode)
        if analytic0 is not None and angle == "0":
            np.testing.assert_allclose(g, analytic0(), atol=1e-15, err_msg=mode)
        if identity is not None:
            np.testing.assert_allclose(g, identity(), atol=1e-12, err_msg=mode)


@pytest.mark.parametrize("case,angle", _grad_params("f32"))
def test_gradients_float32(case, angle):
    i = list(GRAD_ANGLES).index(angle)
    _, _, analytic0, identity = GRAD_CASES[case]
    g64 = _grads("f64@f32")[0][case]["grad"][i]
    scale = max(1.0, np.abs(g64).max())
    for mode, g in _grads("f32")[0][case].items():
        g = g[i]
        assert g.dtype == np.float32
        assert np.all(np.isfinite(g)), (mode, g)
        err = np.abs(g - g64).max() / scale
        assert err <= GRAD32_TOL, (mode, err)
        if analytic0 is not None and angle == "0":
            np.testing.assert_allclose(g, analytic0(), atol=GRAD32_TOL * scale, err_msg=mode)
        if identity is not None:
            np.testing.assert_allclose(g, identity(), atol=GRAD32_TOL * scale, err_msg=mode)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_jacobian_of_exp_at_zero_is_half_identity(dtype):
    expected = np.concatenate([np.zeros((1, 3)), 0.5 * np.eye(3)])
    for mode in (jax.jacfwd, jax.jacrev):
        jac = np.asarray(fast_jit(mode(so3.exp))(jnp.zeros(3, dtype)))
        assert jac.dtype == dtype
        np.testing.assert_allclose(jac, expected, atol=0)


# --------------------------------------------------------------------------- 5. float32 values


def _value_refs(phi64):
    """References in float64 (scipy / series) for rotation vectors phi64."""
    return {
        "exp": sp_quat(Rotation.from_rotvec(phi64), canonical=False),
        "exp_matrix": Rotation.from_rotvec(phi64).as_matrix(),
        "right_jacobian": np_jr_series(phi64),
        "right_jacobian_inv": np.linalg.inv(np_jr_series(phi64)),
    }


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_values_at_edge_angles(dtype):
    tol = TOL32 if dtype == jnp.float32 else TOL64
    phi = jnp.asarray(edge_rotvecs(), dtype)
    phi64 = np.array(phi, np.float64)  # the exact input the library saw (writable copy)
    refs = _value_refs(phi64)
    for name, ref in refs.items():
        out = np.asarray(getattr(J, name)(phi))
        assert out.dtype == dtype
        scale = np.maximum(1.0, np.abs(ref).max())
        if name == "exp":
            assert_quat_close(out, ref, tol)
        else:
            np.testing.assert_allclose(out, ref, atol=tol * scale, err_msg=name)
    # log: input quaternions rounded to dtype; the reference is scipy's log of those same
    # numbers (scipy normalises, and Log(s q) = Log(q) for s > 0, so that is exact).
    q = np.asarray(np_exp_quat(phi64), dtype)
    q64 = np.array(q, np.float64)
    for qq, qq64 in ((q, q64), (-q, -q64)):
        out = np.asarray(J.log(jnp.asarray(qq)))
        assert out.dtype == dtype
        assert_rotvec_close(out, sp_rot(qq64).as_rotvec(), tol * PI)
    R = jnp.asarray(Rotation.from_rotvec(phi64).as_matrix(), dtype)
    out = np.asarray(J.log_matrix(R))
    # R rounded to float32 is not exactly orthogonal: the reference is scipy's (nearest
    # orthogonal) log of the same numbers; near π the rounding of R moves the angle by ~ulps.
    assert_rotvec_close(out, Rotation.from_matrix(np.asarray(R, np.float64)).as_rotvec(), tol * PI)


# --------------------------------------------------------------------------- 6. converters


def test_xyzw_wxyz_vs_scipy(rng):
    rot = Rotation.from_quat(random_unit_quats(rng, N))
    xyzw = rot.as_quat()
    wxyz = np.asarray(J.xyzw_to_wxyz(jnp.asarray(xyzw)))
    # The converted quaternion, read as Hamilton [w, x, y, z] by the numpy formula, is scipy's R.
    w, v = wxyz[:, 0], wxyz[:, 1:]
    R_formula = (
        (2 * w**2 - 1)[:, None, None] * np.eye(3)
        + 2 * w[:, None, None] * np_skew(v)
        + 2 * v[:, :, None] * v[:, None, :]
    )  # Hamilton R(w, v) = (2w² - 1) I + 2w[v]x + 2vvᵀ
    np.testing.assert_allclose(R_formula, rot.as_matrix(), atol=TOL64)
    np.testing.assert_allclose(J.wxyz_to_xyzw(jnp.asarray(wxyz)), xyzw, atol=0)
    seq = np.array([1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(J.xyzw_to_wxyz(seq), [4.0, 1.0, 2.0, 3.0])
    np.testing.assert_array_equal(J.wxyz_to_xyzw(seq), [2.0, 3.0, 4.0, 1.0])


def test_jpl_to_hamilton(rng):
    qbar = random_unit_quats(rng, N)  # JPL ^I_G q̄ = [q1, q2, q3, q4], scalar last
    C = np_jpl_C(qbar)  # R_GtoI
    q_wb = np.asarray(J.jpl_to_hamilton(jnp.asarray(qbar)))
    # The Hamilton quaternion represents R_WB = Cᵀ (checked with scipy).
    np.testing.assert_allclose(sp_rot(q_wb).as_matrix(), np.swapaxes(C, -1, -2), atol=TOL64)
    np.testing.assert_allclose(
        J.quat_to_matrix(jnp.asarray(q_wb)), np.swapaxes(C, -1, -2), atol=TOL64
    )
    np.testing.assert_allclose(J.hamilton_to_jpl(jnp.asarray(q_wb)), qbar, atol=0)


def test_hamilton_to_jpl(rng):
    rot = Rotation.from_quat(random_unit_quats(rng, N))  # R_WB
    q_wb = sp_quat(rot, canonical=False)
    qbar = np.asarray(J.hamilton_to_jpl(jnp.asarray(q_wb)))
    np.testing.assert_allclose(np_jpl_C(qbar), np.swapaxes(rot.as_matrix(), -1, -2), atol=TOL64)


# --------------------------------------------------------------------------- 7. Euler angles


def _random_euler(rng, n, max_pitch=1.4):
    return np.stack(
        [
            rng.uniform(-PI, PI, n),
            rng.uniform(-max_pitch, max_pitch, n),
            rng.uniform(-PI, PI, n),
        ],
        -1,
    )


def _wrap(a):
    return (a + PI) % (2 * PI) - PI


def _sp_euler(chi):
    """scipy rotation of our [roll, pitch, yaw] (scipy takes [yaw, pitch, roll] for "ZYX")."""
    return Rotation.from_euler("ZYX", np.asarray(chi)[..., ::-1])


def test_euler_to_quat_and_matrix_vs_scipy(rng):
    chi = _random_euler(rng, N, max_pitch=PI / 2)
    rot = _sp_euler(chi)
    assert_quat_close(J.euler_zyx_to_quat(jnp.asarray(chi)), sp_quat(rot), TOL64)
    np.testing.assert_allclose(J.euler_zyx_to_matrix(jnp.asarray(chi)), rot.as_matrix(), atol=TOL64)


def test_quat_to_euler_vs_scipy(rng):
    chi = _random_euler(rng, N)
    rot = _sp_euler(chi)
    q = sp_quat(rot, canonical=False)
    expected = rot.as_euler("ZYX")[:, ::-1]
    for qq in (q, -q):
        out = np.asarray(J.quat_to_euler_zyx(jnp.asarray(qq)))
        np.testing.assert_allclose(_wrap(out - expected), 0, atol=TOL64)
        np.testing.assert_allclose(_wrap(out - chi), 0, atol=1e-10)
        assert np.all(np.abs(out[:, 1]) <= PI / 2)


def test_euler_rate_matrix_vs_fd(rng):
    # χ(t) = Euler(R(χ) Exp(ω t)) with body rate ω; χ̇(0) = E(χ) ω. Central FD via scipy.
    chi = _random_euler(rng, 50, max_pitch=1.3)
    omega = rng.normal(size=(50, 3))
    R0 = _sp_euler(chi)

    def euler_at(t):
        return (R0 * Rotation.from_rotvec(omega * t)).as_euler("ZYX")[:, ::-1]

    h = 1e-6
    fd = _wrap(euler_at(h) - euler_at(-h)) / (2 * h)
    E = np.asarray(J.euler_rate_matrix(jnp.asarray(chi)))
    # FD accuracy ~1e-9 here (h² |χ'''| + eps/h); |E| grows like 1/cos(pitch) <= ~4.
    np.testing.assert_allclose(np.einsum("nij,nj->ni", E, omega), fd, atol=1e-7, rtol=1e-7)


def test_euler_rate_matrix_blows_up_at_gimbal_lock():
    # Near pitch ±90° the Euler rates of a bounded body rate are ~1/cos(pitch) ≈ 1e4: E is
    # huge, and (checked by FD with a step far below the 1e-4 time scale) correctly so.
    omega = np.array([[0.2, -0.5, 0.4]])
    for sign in (1.0, -1.0):
        chi = np.array([[0.3, sign * (PI / 2 - 1e-4), -0.7]])
        E = np.asarray(J.euler_rate_matrix(jnp.asarray(chi)))
        assert np.abs(E).max() > 1e3
        R0 = _sp_euler(chi)

        def euler_at(t):
            return (R0 * Rotation.from_rotvec(omega * t)).as_euler("ZYX")[:, ::-1]

        h = 1e-9
        fd = _wrap(euler_at(h) - euler_at(-h)) / (2 * h)
        assert np.abs(fd).max() > 1e3
        # FD: truncation ~(h / 1e-4)² ≈ 1e-10 relative; rounding: near the lock the extracted
        # roll/yaw carry ~eps/cos(pitch) ≈ 2e-12 rad, i.e. ~2e-3 after dividing by h, on rates of
        # 1e3-1e4 (rtol 1e-5), and ~1e-6 on the O(1) pitch rate (atol 1e-4).
        np.testing.assert_allclose(np.einsum("nij,nj->ni", E, omega), fd, rtol=1e-5, atol=1e-4)


# --------------------------------------------------------------------------- 8. skew, broadcasting


def test_skew_is_cross_product(rng):
    v, w = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    S = np.asarray(J.skew(jnp.asarray(v)))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", S, w), np.cross(v, w), atol=1e-14)
    np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))


def _sample(kind, rng, shape):
    n = int(np.prod(shape, dtype=int))
    if kind == "quat":
        x = random_unit_quats(rng, n)
    elif kind == "vec":
        x = random_rotvecs(rng, n, max_angle=3.0)
    elif kind == "euler":
        x = _random_euler(rng, n)
    elif kind == "mat":
        x = Rotation.from_quat(random_unit_quats(rng, n)).as_matrix()
    return x.reshape(tuple(shape) + x.shape[1:])


# name -> (input kinds, core output shape)
SIGNATURES = {
    "skew": (("vec",), (3, 3)),
    "quat_mul": (("quat", "quat"), (4,)),
    "quat_conj": (("quat",), (4,)),
    "quat_normalize": (("quat",), (4,)),
    "quat_rotate": (("quat", "vec"), (3,)),
    "quat_to_matrix": (("quat",), (3, 3)),
    "matrix_to_quat": (("mat",), (4,)),
    "exp": (("vec",), (4,)),
    "log": (("quat",), (3,)),
    "exp_matrix": (("vec",), (3, 3)),
    "log_matrix": (("mat",), (3,)),
    "right_jacobian": (("vec",), (3, 3)),
    "right_jacobian_inv": (("vec",), (3, 3)),
    "left_jacobian": (("vec",), (3, 3)),
    "quat_first_order_update": (("quat", "vec"), (4,)),
    "xyzw_to_wxyz": (("quat",), (4,)),
    "wxyz_to_xyzw": (("quat",), (4,)),
    "jpl_to_hamilton": (("quat",), (4,)),
    "hamilton_to_jpl": (("quat",), (4,)),
    "euler_zyx_to_quat": (("euler",), (4,)),
    "euler_zyx_to_matrix": (("euler",), (3, 3)),
    "quat_to_euler_zyx": (("quat",), (3,)),
    "euler_rate_matrix": (("euler",), (3, 3)),
}


def test_signatures_cover_the_api():
    assert set(SIGNATURES) | {"quat_identity"} == set(so3.__all__)


def _apply_all(inputs):
    """Every library function on its inputs; one compiled function per input shapes."""
    return {name: getattr(so3, name)(*args) for name, args in inputs.items()}


_APPLY_ALL = fast_jit(_apply_all)


def _all_inputs(rng, shapes_per_arg):
    return {
        name: tuple(_sample(k, rng, shape) for k, shape in zip(kinds, shapes_per_arg(len(kinds))))
        for name, (kinds, _) in SIGNATURES.items()
    }


@pytest.mark.parametrize("batch", [(), (7,), (2, 3)], ids=str)
def test_broadcasting_matches_loop(batch, rng):
    inputs = _all_inputs(rng, lambda nargs: [batch] * nargs)
    out = jax.tree.map(np.asarray, _APPLY_ALL(inputs))
    for name, (_, core) in SIGNATURES.items():
        assert out[name].shape == tuple(batch) + core, name
    # Loop over the batch elements, each a single-sample call (one compile for shape ()).
    for idx in np.ndindex(*batch):
        single = _APPLY_ALL(jax.tree.map(lambda a: a[idx], inputs))
        for name in SIGNATURES:
            np.testing.assert_allclose(
                out[name][idx], single[name], rtol=1e-14, atol=1e-14, err_msg=name
            )


def test_binary_broadcast_between_arguments(rng):
    # Leading shapes (2, 1) and (3,) broadcast to (2, 3).
    binary = [n for n, (kinds, _) in SIGNATURES.items() if len(kinds) == 2]
    inputs = {
        n: (_sample(SIGNATURES[n][0][0], rng, (2, 1)), _sample(SIGNATURES[n][0][1], rng, (3,)))
        for n in binary
    }
    out = jax.tree.map(np.asarray, _APPLY_ALL(inputs))
    for i, j in np.ndindex(2, 3):
        single = _APPLY_ALL({n: (a[i, 0], b[j]) for n, (a, b) in inputs.items()})
        for n in binary:
            assert out[n].shape == (2, 3) + SIGNATURES[n][1], n
            np.testing.assert_allclose(out[n][i, j], single[n], atol=1e-14, err_msg=n)


def test_quat_identity():
    q = np.asarray(fast_jit(functools.partial(so3.quat_identity, (2, 3)))())
    assert q.shape == (2, 3, 4) and q.dtype == np.float32  # documented default dtype
    np.testing.assert_array_equal(q, np.broadcast_to([1.0, 0, 0, 0], (2, 3, 4)))
    assert jax.eval_shape(lambda: so3.quat_identity(dtype=jnp.float64)).dtype == np.float64
    np.testing.assert_array_equal(sp_rot(q[0, 0].astype(np.float64)).as_matrix(), np.eye(3))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_dtype_preserved(dtype, rng):
    # Abstract evaluation only (no compile): float32 in -> float32 out, also under x64.
    inputs = jax.tree.map(lambda a: jnp.asarray(a, dtype), _all_inputs(rng, lambda n: [(3,)] * n))
    out = jax.eval_shape(_apply_all, inputs)
    for name, o in out.items():
        assert o.dtype == dtype, name


# --------------------------------------------------------------------------- 9. first-order update


def test_quat_first_order_update_vs_exact_reduced_angle(rng):
    q = random_unit_quats(rng, N)
    phi = np.concatenate(
        [random_rotvecs(rng, N - 3, max_angle=2.0), np.zeros((1, 3)), 1e-8 * AXES[:2]]
    )
    out = np.asarray(J.quat_first_order_update(jnp.asarray(q), jnp.asarray(phi)))
    # φ' = φ/|φ| · 2 atan(|φ|/2)  (φ' = 0 at φ = 0).
    th = np.linalg.norm(phi, axis=-1, keepdims=True)
    scale = np.where(th > 0, 2 * np.arctan(th / 2) / np.where(th > 0, th, 1.0), 1.0)
    dq = np_exp_quat(phi * scale)
    # Exact, sign included: q ⊗ Exp(φ') with Exp's w = cos(atan(θ/2)) > 0.
    np.testing.assert_allclose(out, np_qmul(q, dq), atol=TOL64)
    assert_quat_close(out, sp_quat(sp_rot(q) * Rotation.from_rotvec(phi * scale)), TOL64)
    np.testing.assert_allclose(out[N - 3], q[N - 3], atol=1e-15)  # normalisation: ~ulps
