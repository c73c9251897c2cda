"""Fast XLA-CPU kernels of propagation: the mean and the final covariance of every scheme
(exact quaternion exponential; closed-form or autodiff Jacobian blocks), on the
structure-of-arrays layout of :mod:`jaximu.kernels.soa` (why that layout: docs/DESIGN.md).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaximu.geometry import sensor, so3
from jaximu.geometry._vec import V3
from jaximu.kernels.lane_directions import LANE_DIRECTIONS
from jaximu.kernels.lane_forms import LANE_FORMS, LaneForm, _sincos, mean_step
from jaximu.kernels.lane_math import (
    SOA,
    _bmm,
    _bt,
    _materialise,
    _quat_normalize,
    exp_jr,
    half_angle_jr,
)
from jaximu.kernels.soa import (
    HALO,
    _components,
    _stack_last,
    _time_chunks,
    block_lanes,
    run_blocked,
)
from jaximu.schemes import _blocks, world
from jaximu.schemes._blocks import UPPER, block, structured_update
from jaximu.schemes._jvp_blocks import blocks_by_jvp
from jaximu.schemes.integrators import GIMBAL_LOCK_COS

QUATERNION = LANE_FORMS["quaternion"]


def _enter_world(omega: V3, p: V3, v: V3, coriolis) -> V3:
    """The velocity the still-world step starts from (the transported one for "exact")."""
    return world.to_inertial_v3(omega, p, v) if coriolis == "exact" else v


def _leave_world(q, p, v, h, g: V3, omega: V3, coriolis, form: LaneForm = QUATERNION):
    """The still-world step's end ``(q, p, v)`` (tuples of lanes; ``q`` in the attitude
    form ``form``) back in the turning world: out of the step's inertial frame ("exact"), or
    GTSAM ≤ 4.2's increments at the end."""
    if coriolis == "exact":
        dth, Q, dp, dv = world.leave_inertial_terms(omega.stack(), h, g.stack())
        p, v = world.leave_inertial_v3(omega, Q, V3.of(dp), V3.of(dv), V3(*p), V3(*v))
        return form.rotate_left(q, dth), tuple(p), tuple(v)
    dth, dp, dv = world.coriolis_increments_v3(omega, V3(*p), V3(*v), h, coriolis == "second_order")
    return form.rotate_left(q, dth.stack()), tuple(V3(*p) + dp), tuple(V3(*v) + dv)


def rotating_mean_step(
    scheme,
    q,
    p: V3,
    v: V3,
    omega0,
    f0,
    omega1,
    f1,
    h,
    g: V3,
    omega: V3,
    coriolis,
    form: LaneForm = QUATERNION,
):
    """:func:`jaximu.propagate.rotating_step` on lanes: the still-world step in the inertial
    frame of the step's start (``coriolis="exact"``) or followed by GTSAM ≤ 4.2's increments
    (:mod:`jaximu.world` holds both)."""
    v = _enter_world(omega, p, v, coriolis)
    q, p, v = mean_step(scheme, q, p, v, omega0, f0, omega1, f1, h, g, form=form)
    return _leave_world(q, p, v, h, g, omega, coriolis, form)


def _lock(locked, q, p, v):
    """The Euler-angle form's pitch ±90° singularity on lanes (as the generic kernels'
    :func:`jaximu.propagate.mean_body`): ``locked`` ``(B,)`` grows by the lanes whose new
    pitch reaches it, and their state ``(q, p, v)`` is NaN from that step on, never a silently
    wrong attitude. Returns ``(q, p, v, (locked,))``, the kernels' carry."""
    locked = locked | (_sincos(q[1])[1] < GIMBAL_LOCK_COS)
    nan = lambda t: tuple(jnp.where(locked, jnp.nan, x) for x in t)  # noqa: E731
    return nan(q), nan(p), nan(v), (locked,)


def _sensor_samples(pose_q, pose_p, b_g, n_samples, tangential):
    """The ``samples`` hook of :func:`jaximu.kernels.soa._time_chunks` for a block's lanes of a
    sensor at ``(q_BS, p_BS)`` (``None``: no sensor pose), ``b_g`` the body-frame gyro bias's
    components (:func:`jaximu.sensor.chunk_to_body`)."""
    if pose_q is None:
        return None
    return sensor.chunk_to_body(
        so3.quat_to_matrix(pose_q), V3(*b_g), V3(*_components(pose_p)), n_samples, tangential, HALO
    )


QUATERNION_FORMS = ("quaternion", "quaternion_first_order")


def _unit_start(form, q):
    """The lanes' start attitude (``(B, form.size)``) as components; a quaternion form's
    normalised, inside the kernel (:func:`jaximu.engine._inputs.unit_start` does it for the other
    kernels; an operation outside the kernel is one more module for XLA:CPU to compile)."""
    x = _components(q)
    return _quat_normalize(x) if form.name in QUATERNION_FORMS else x


def propagate_mean(
    scheme,
    q,
    p,
    v,
    b_g,
    b_a,
    gyro,
    accel,
    dt,
    g,
    save_all,
    omega=None,
    coriolis="exact",
    form: LaneForm = QUATERNION,
    pose=None,
    tangential=True,
    n_samples=None,
):
    """Flat batch: q ``(B, form.size)`` (the attitude form's state, :data:`LANE_FORMS`: a
    quaternion ``(B, 4)``, a matrix ``(B, 9)`` row-major, Euler angles ``(B, 3)``),
    p/v/b_g/b_a ``(B, 3)``, gyro/accel
    ``(B, T, 3)`` (``T + 1`` samples for a scheme that uses sample k+1: the last one ends the
    last step), dt ``(T,)`` or ``(B, T)``, g ``(3,)`` or ``(B, 3)``; omega (a rotating
    world, :mod:`jaximu.world`) ``None``, ``(3,)`` or ``(B, 3)``. Returns final ``(q, p, v)``
    (B, ·) or, with save_all, the ``(B, T, ·)`` trajectories, ``q`` in the form; for Euler
    angles a 4th output, the lanes that reached the pitch singularity (``(B, 1)`` or
    ``(B, T, 1)`` bool: from that step on their states are NaN, as the generic kernel's).

    ``pose``: ``None``, or the samples are a sensor's at ``(q_BS, p_BS)`` (``(4,)``, ``(3,)``
    shared or ``(B, ·)``) and ``b_g``, ``b_a`` the biases in the body frame: the samples
    move into the body frame in the kernel's time chunks (:func:`jaximu.sensor.chunk_to_body`;
    ``tangential`` as :func:`jaximu.sensor.to_body`, ``n_samples`` the samples the user gave)."""
    B = gyro.shape[0]
    shared_dt = dt.ndim == 1
    shared_g = g.ndim == 1
    rotating = omega is not None
    shared_w = not rotating or omega.ndim == 1
    euler = form.name == "euler_angles"
    pose_q, pose_p = (None, None) if pose is None else pose
    # the pose's rotation and lever arm are each shared or per lane (a vmap over lever arms)
    shared_pose = tuple(x is None or x.ndim == 1 for x in (pose_q, pose_p))

    def block(q, p, v, b_g, b_a, gyro, accel, dt, g, omega, pose_q, pose_p):
        consts = (
            _components(b_g),
            _components(b_a),
            _components(g),
            _components(omega) if rotating else (),
        )
        carry = (_unit_start(form, q), _components(p), _components(v))
        if euler:  # and the locked flag of each lane
            carry = carry + ((jnp.zeros(q.shape[:1], bool),),)

        def step(c, w, a, h, consts):
            bg, ba, gv = (V3(*x) for x in consts[:3])
            omega0, f0 = V3(*w[:3]) - bg, V3(*a[:3]) - ba
            omega1, f1 = (V3(*w[3:]) - bg, V3(*a[3:]) - ba) if len(w) == 6 else (omega0, f0)
            q, p, v = c[:3]
            if rotating:
                q, p, v = rotating_mean_step(
                    scheme,
                    q,
                    V3(*p),
                    V3(*v),
                    omega0,
                    f0,
                    omega1,
                    f1,
                    h,
                    gv,
                    V3(*consts[3]),
                    coriolis,
                    form,
                )
            else:
                q, p, v = mean_step(
                    scheme, q, V3(*p), V3(*v), omega0, f0, omega1, f1, h, gv, form=form
                )
            return _lock(c[3][0], q, p, v) if euler else (q, p, v)

        save = (lambda c: tuple(_stack_last(x) for x in c)) if save_all else None
        carry, bufs = _time_chunks(
            step,
            carry,
            gyro,
            accel,
            dt,
            consts,
            save,
            next_sample=scheme.uses_next_sample,
            samples=_sensor_samples(pose_q, pose_p, consts[0], n_samples, tangential),
        )
        if save_all:
            return bufs
        return tuple(_stack_last(x) for x in carry)

    # dt, g, omega and a pose shared by all lanes are read whole by every block
    return run_blocked(
        block,
        B,
        block_lanes(gyro.dtype),
        q,
        p,
        v,
        b_g,
        b_a,
        gyro,
        accel,
        dt,
        g,
        omega,
        pose_q,
        pose_p,
        whole=(False,) * 7 + (shared_dt, shared_g, shared_w) + shared_pose,
    )


def dense_to_lanes(P):
    """``(B, 15, 15)`` -> the 15 upper blocks as ``(3, 3, B)`` lanes, in :data:`UPPER` order:
    :func:`jaximu.schemes._blocks.dense_to_blocks` in the lane layout (``SOA.from_arrays``)."""
    return tuple(SOA.from_arrays(X) for X in _blocks.dense_to_blocks(P).values())


def lanes_to_dense(Pb):
    """The 15 upper ``(3, 3, B)`` blocks (:data:`UPPER` order) -> symmetric ``(B, 15, 15)``:
    :func:`jaximu.schemes._blocks.blocks_to_dense` assembled in the lane layout (the lower
    blocks by :func:`jaximu.schemes._blocks.block`), the batch axis moved first at the end."""
    d = dict(zip(UPPER, Pb))
    D = jnp.concatenate(
        [jnp.concatenate([block(d, i, j, SOA) for j in range(5)], 1) for i in range(5)], 0
    )
    return jnp.moveaxis(D, -1, 0)


def blocks_autodiff(
    scheme,
    q,
    p,
    v,
    omega0,
    f0,
    omega1,
    f1,
    h,
    g,
    lever=None,
    world_error=False,
    form: LaneForm = QUATERNION,
):
    """One step of ``scheme`` and the blocks of its ``Φ`` on SoA lanes, by autodiff:
    :func:`jaximu.schemes._jvp_blocks.blocks_by_jvp` (the 9 non-structural directions in
    three groups, each a ``vmap`` of ``jax.jvp`` of :func:`jaximu.kernels.lane_forms.mean_step`,
    direction axis major, lanes minor) in the lane layout; the same function makes the
    array layout's blocks (:func:`jaximu.engine.jacobians.blocks_autodiff`). The attitude's
    tangents and rows are those of ``form`` (:data:`LANE_FORMS`; a quaternion: ``q ⊗ [0, ½
    e_j]`` and ``2 vec(q⁺* ⊗ δq⁺)``, the tangent of ``Log(q̂⁺* q⁺)``; a matrix: ``R [e_j]x``,
    ``vee(R⁺ᵀ δR⁺)``). ``lever`` (a :class:`V3`, or ``None``): samples moved from a sensor
    at that lever arm, whose specific force moves by ``K δb_g``
    (:func:`jaximu.sensor.centripetal_jacobian`). ``world_error``: the rotation error in the
    world frame (``Exp(δθ_W) ⊗ q``: tangent ``[0, ½ e_j] ⊗ q``, rows ``2 vec(δq⁺ ⊗ q⁺*)``),
    whose ``A`` block is the identity (returned as ``"I"``, not formed).

    Returns:
        ``((q⁺, p⁺, v⁺), Blocks)`` with ``(3, 3, B)`` blocks.
    """
    lanes = q[0].shape

    def step(q, omega0, omega1, f0, f1):
        return mean_step(scheme, q, p, v, omega0, f0, omega1, f1, h, g, form=form)

    def k_cols(omega):  # direction j moves f by the column K e_j: component i is K[i, j]
        K = jnp.broadcast_to(sensor.centripetal_jacobian(omega, lever, SOA), (3, 3) + lanes)
        return V3(K[0], K[1], K[2])

    return blocks_by_jvp(
        step,
        q,
        omega0,
        omega1,
        f0,
        f1,
        h,
        form.tangents(q, world_error),
        lambda tq1, q1: form.rows(tq1, q1, world_error),
        LANE_DIRECTIONS,
        None if lever is None else k_cols,
        identity_A=world_error,
    )


def cov_step_blocks(
    scheme,
    jacobians,
    carry,
    omega0,
    f0,
    omega1,
    f1,
    h,
    g,
    qc,
    omega=None,
    coriolis="exact",
    lever=None,
    world_error=False,
    form: LaneForm = QUATERNION,
    transition=False,
    qc_scale=None,
):
    """Mean + covariance step of any scheme on the SoA layout: the blocks of ``Φ`` in closed
    form (``jacobians="analytic"``, :meth:`jaximu.integrators.Scheme.blocks`) or by autodiff
    of the step (:func:`blocks_autodiff`), and the block update of
    :func:`jaximu.schemes._blocks.structured_update`. ``carry = (q, p, v, Pb)``. ``omega`` (a
    :class:`V3`, or ``None``): the world turns, and the step runs between the world's maps
    (:func:`jaximu.world.covariance_step`). ``lever`` (a :class:`V3`, or ``None``): the
    samples are a sensor's at that lever arm, moved to the body (:mod:`jaximu.sensor`).
    ``world_error`` (a still world only): ``Pb``'s rotation error is in the world frame,
    ``δθ_W = R δθ`` (:func:`world_error_blocks`), where ``Φ_θθ = I``. ``form``: the
    attitude form of ``q`` (:data:`LANE_FORMS`; closed forms only for the exact ones).
    ``transition``: return the step's whole transition too, as block rows
    (:func:`jaximu.schemes._blocks.transition_rows`, between the world's maps in a turning world),
    with the ``p_over_v`` of :func:`jaximu.schemes._blocks.rows_product` (``None`` where
    they have no such structure). ``qc_scale``: as
    :func:`jaximu.schemes._blocks.structured_update`'s."""
    q, p, v, Pb = carry
    if omega is not None:
        v = tuple(_enter_world(omega, V3(*p), V3(*v), coriolis))
    if jacobians == "analytic":
        phi_end = scheme.points(omega0, f0, omega1, f1, h)[1]
        half = half_angle_jr(phi_end.dot(phi_end))  # one half angle for the mean and Φ
        q1, p1, v1 = mean_step(
            scheme, q, V3(*p), V3(*v), omega0, f0, omega1, f1, h, g, half[:2], form
        )
        R = form.matrix(q, q[0].dtype)
        b = scheme.blocks(R, omega0, f0, omega1, f1, h, SOA, end=exp_jr(phi_end, half), lever=lever)
        if world_error:  # Φ' = T⁺ Φ Tᵀ, T = blockdiag(R, I, I, I, I): A' = R⁺ A Rᵀ = I
            Rt = _bt(R)
            b = b._replace(
                A="I",
                B=_bmm(form.matrix(q1, q[0].dtype), b.B),
                Cv=_bmm(b.Cv, Rt),
                Cp=None if b.Cp is None else _bmm(b.Cp, Rt),
            )
    else:
        (q1, p1, v1), b = blocks_autodiff(
            scheme, q, V3(*p), V3(*v), omega0, f0, omega1, f1, h, g, lever, world_error, form
        )
    qc4 = (qc[0:3], qc[3:6], qc[6:9], qc[9:12])
    s = scheme.p_over_v(h)
    rows = None
    if transition:  # the blocks are read by the transition's products too: computed once
        b = SOA.barrier(b)
        rows = _blocks.transition_rows(b, SOA, s)
    if omega is None:
        new = structured_update(dict(zip(UPPER, Pb)), b, qc4, SOA, s, qc_scale)
    else:
        pre, post = world.error_maps(omega.stack(), h, coriolis, SOA)
        new = world.covariance_step(
            dict(zip(UPPER, Pb)),
            b,
            qc4,
            omega.stack(),
            h,
            coriolis,
            SOA,
            s,
            maps=(pre, post),
            qc_scale=qc_scale,
        )
        if transition:
            rows = _blocks.rows_product(post, rows, SOA)
            rows = rows if pre is None else _blocks.rows_product(rows, pre, SOA)
        q1, p1, v1 = _leave_world(q1, p1, v1, h, g, omega, coriolis, form)
    out = (q1, p1, v1, tuple(new[k] for k in UPPER))
    # the rows, and s where their p row is s times their v row (a still world)
    return out + ((rows, s if omega is None else None),) if transition else out


def discrete_variances(h, var, padded=False):
    """A step's noise variances ``σ² / h`` (:meth:`jaximu.noise.ImuNoise.discrete_variances`)
    as twelve per-lane scalars, and a factor of all of them (or ``None``): steps ``h`` shared
    ``()`` or per lane ``(Bc,)``, ``var`` ``(12,)`` shared or ``(Bc, 12)``. Shared ``σ²``
    with per-lane steps (a sequence's time chunks side by side) stay shared, their ``1 / h``
    the factor that :func:`jaximu.schemes._blocks.structured_update` applies once per noise
    block (per-lane variances cost the update a tenth more). ``padded``: steps of ``h = 0``
    are a chunk's padding (``G = 0``), with no noise rather than ``0 · ∞``; otherwise a step
    too short for ``σ² / h`` (a float32 ``dt`` of 1e-45, which XLA's CPU flushes to zero)
    gives the non-finite value the engine's output check names."""
    if padded:
        h = jnp.where(h > 0, h, jnp.ones_like(h))
    if var.ndim == 1 and jnp.ndim(h):
        return tuple(var[i] for i in range(12)), 1.0 / h
    qc = var / (h[..., None] if jnp.ndim(h) else h)
    return tuple(qc[..., i] for i in range(12)), None


def world_error_frame(omega, save_all, form: LaneForm) -> bool:
    """Whether the covariance kernel keeps the rotation error in the world frame
    (:func:`world_error_blocks`): the final covariance of a quaternion form in a still world
    (for a quaternion form its map in and out normalises ``q``, which a matrix cannot be;
    Euler angles' step is no right multiplication of ``R``, so their ``Φ_θθ`` would not be
    ``I`` there)."""
    return omega is None and not save_all and form.size == 4


def transition_pattern(rotating, world_error):
    """The form of a product of the covariance kernel's step transitions
    (:func:`jaximu.schemes._blocks.conform_rows`): the structure of the module docstring of
    :mod:`jaximu.schemes._blocks` (``Φ_θθ = I`` with ``world_error``), which products keep; in a
    turning world the error maps fill the p and v rows (:func:`jaximu.world.error_map_rows`)."""
    if rotating:
        pv = {j: "X" for j in range(5)}
        return {0: {0: "X", 3: "X"}, 1: dict(pv), 2: dict(pv)}
    return {
        0: {0: "I" if world_error else "X", 3: "X"},
        1: {0: "X", 1: "I", 2: "s", 3: "X", 4: "X"},
        2: {0: "X", 2: "I", 3: "X", 4: "X"},
    }


def world_error_blocks(Pb, q, inverse=False):
    """``T P Tᵀ`` with ``T = blockdiag(R(q), I, I, I, I)`` on the 15 upper blocks
    (``inverse``: ``Tᵀ P T``): the covariance of the body-frame rotation error ``δθ`` as that
    of the world-frame one ``δθ_W = R δθ``, or back. In the world frame ``Φ_θθ = I`` (the
    same change of coordinates as the preintegration kernel's, :mod:`jaximu.kernels.fast_preint`),
    which saves the covariance update eight 3×3 products a step (closed-form blocks pay two
    to change frame; autodiff makes its blocks in that frame). ``T`` must be a rotation for
    the map back to undo the map in: ``q`` is the kernel's, normalised at its start
    (:func:`_unit_start`, also under ``jit``) and kept unit by every step."""
    R = QUATERNION.matrix(q, q[0].dtype)
    new = _blocks.congruence(dict(zip(UPPER, Pb)), {0: {0: _bt(R) if inverse else R}}, SOA)
    return tuple(new[k] for k in UPPER)


def propagate_cov(
    q,
    p,
    v,
    b_g,
    b_a,
    P0,
    gyro,
    accel,
    dt,
    g,
    var,
    scheme,
    jacobians,
    omega=None,
    coriolis="exact",
    lever=None,
    save_all=False,
    form: LaneForm = QUATERNION,
    pose=None,
    tangential=True,
    n_samples=None,
    transition=None,
    padded=False,
):
    """Mean and covariance: the final ``(q, p, v, P)`` ``(B, ·)``, or with ``save_all`` those
    after every step, ``(B, T, ·)`` (``P`` ``(B, T, 15, 15)``). ``var``: the noise's continuous-time
    variances ``σ²`` (:meth:`jaximu.noise.ImuNoise.variances`), ``(12,)`` shared by all lanes
    or ``(B, 12)`` per lane; a step's are ``σ² / dt`` (:func:`discrete_variances`), none for
    a step of ``dt = 0`` where ``padded`` (a time chunk's padding, :mod:`jaximu.engine._chunked`).
    ``scheme``: a :class:`jaximu.integrators.Scheme` (inputs with ``T + 1`` samples when it
    uses sample k+1); ``jacobians``: ``"analytic"`` or ``"autodiff"`` (:func:`cov_step_blocks`);
    ``omega``: ``None``, ``(3,)`` or ``(B, 3)``, the world's rate (:mod:`jaximu.world`);
    ``lever``: ``None``, ``(3,)`` or ``(B, 3)``, the lever arm of a sensor's samples
    (:func:`cov_step_blocks`); ``form``: the attitude form of ``q`` ``(B, form.size)``
    (:data:`LANE_FORMS`), which the outputs keep; ``pose``, ``tangential``, ``n_samples``:
    a sensor's samples, moved in the time chunks (:func:`propagate_mean`).

    ``transition``: a time chunk's summary (:mod:`jaximu.engine._chunked`), ``None`` or the form of
    its transition's block rows (:func:`jaximu.schemes._blocks.conform_rows`' ``pattern``). The
    kernel then also multiplies the steps' transitions, and returns ``(q, p, v, P blocks,
    Φ leaves)`` (final state only): the 15 upper blocks of ``P`` ``(B, 3, 3)`` each and the
    leaves of ``Φ`` (:func:`jaximu.schemes._blocks.rows_leaves`: ``(B, 3, 3)`` blocks, ``(B,)``
    scalars), both in the kernel's frame (the world-frame rotation error of a final
    covariance, :func:`world_error_blocks`, is not mapped back); Euler angles' locked flags
    after them."""
    B = gyro.shape[0]
    shared_dt = dt.ndim == 1
    shared_g = g.ndim == 1
    rotating = omega is not None
    shared_w = not rotating or omega.ndim == 1
    shared_r = lever is None or lever.ndim == 1
    shared_n = var.ndim == 1
    world_error = world_error_frame(omega, save_all, form)
    assert transition is None or not save_all
    euler = form.name == "euler_angles"
    pose_q, pose_p = (None, None) if pose is None else pose
    # the pose's rotation and lever arm are each shared or per lane (a vmap over lever arms)
    shared_pose = tuple(x is None or x.ndim == 1 for x in (pose_q, pose_p))

    def block(q, p, v, b_g, b_a, P0, gyro, accel, dt, g, var, omega, lever, pose_q, pose_p):
        consts = (
            _components(b_g),
            _components(b_a),
            _components(g),
            var,
            (_components(omega) if rotating else None),
            (None if lever is None else _components(lever)),
        )
        carry = (_unit_start(form, q), _components(p), _components(v), dense_to_lanes(P0))
        if world_error:
            carry = carry[:3] + (world_error_blocks(carry[3], carry[0]),)
        if euler:  # and the locked flag of each lane
            carry = carry + ((jnp.zeros(q.shape[:1], bool),),)
        if transition is not None:  # and the product of the steps' transitions (identity)
            dtype = q.dtype
            block_shape, scalar_shape = (3, 3, q.shape[0]), (q.shape[0],)

            def conform(rows):
                return _blocks.rows_leaves(
                    _blocks.conform_rows(rows, transition, block_shape, scalar_shape, dtype, SOA),
                    transition,
                )

            # the block columns the pattern holds (the product's others are not formed)
            columns = sorted({j for row in transition.values() for j in row})
            carry = carry + (tuple(conform({})),)

        def step(c, w, a, h, consts):
            if transition is None:
                return cov_step(c, w, a, h, consts)
            out = cov_step(c[:-1], w, a, h, consts, True)
            acc = _blocks.rows_from_leaves(c[-1], transition)
            rows, p_over_v = out[-1]
            product = _blocks.rows_product(rows, acc, SOA, columns, p_over_v)
            return out[:-1] + (tuple(conform(product)),)

        def cov_step(c, w, a, h, consts, with_transition=False):
            bg, ba, gv, ln, wv, rv = consts
            qc, qc_scale = discrete_variances(h, ln, padded)
            bg, ba = V3(*bg), V3(*ba)
            omega0, f0 = V3(*w[:3]) - bg, V3(*a[:3]) - ba
            omega1, f1 = (V3(*w[3:]) - bg, V3(*a[3:]) - ba) if len(w) == 6 else (omega0, f0)
            # the step's inputs in memory: read through the scan's dynamic slice inside the
            # 3-D block fusions they stop LLVM from vectorising them
            omega0, f0, omega1, f1, h, qc, qc_scale = _materialise(
                (omega0, f0, omega1, f1, h, qc, qc_scale)
            )
            out = cov_step_blocks(
                scheme,
                jacobians,
                c[:4],
                omega0,
                f0,
                omega1,
                f1,
                h,
                V3(*gv),
                qc,
                None if wv is None else V3(*wv),
                coriolis,
                None if rv is None else V3(*rv),
                world_error,
                form,
                with_transition,
                qc_scale,
            )
            if not euler:
                return out
            # the covariance follows the NaN state from the next step's blocks, as the
            # generic kernel's
            q, p, v, locked = _lock(c[4][0], *out[:3])
            return (q, p, v, out[3], locked) + out[4:]

        # every step: q, p, v and the 15 upper blocks, each (Bc, 9) (a block's 3×3 in a
        # row): the dense matrices are assembled once, after the kernel (assembling them at
        # every step inside it ran 0.65 M samples/s against 0.83, float32, 1024 × 200)
        def save(c):
            return (_stack_last(c[0]), _stack_last(c[1]), _stack_last(c[2])) + tuple(
                jnp.moveaxis(X, -1, 0).reshape(-1, 9) for X in c[3]
            )

        carry, bufs = _time_chunks(
            step,
            carry,
            gyro,
            accel,
            dt,
            consts,
            save if save_all else None,
            next_sample=scheme.uses_next_sample,
            samples=_sensor_samples(pose_q, pose_p, consts[0], n_samples, tangential),
        )
        q, p, v, Pb = carry[:4]
        locked = (carry[4][0],) if euler else ()  # (Bc,): by the last step
        if save_all:
            return tuple(bufs) + locked
        if transition is not None:  # lanes first, as run_blocked joins them
            return (
                _stack_last(q),
                _stack_last(p),
                _stack_last(v),
                tuple(jnp.moveaxis(X, -1, 0) for X in Pb),
                tuple(jnp.moveaxis(X, -1, 0) for X in carry[-1]),
            ) + locked
        if world_error:
            Pb = world_error_blocks(Pb, q, inverse=True)
        return (_stack_last(q), _stack_last(p), _stack_last(v), lanes_to_dense(Pb)) + locked

    # values shared by all lanes (and a missing lever arm) are read whole by every block
    out = run_blocked(
        block,
        B,
        block_lanes(gyro.dtype),
        q,
        p,
        v,
        b_g,
        b_a,
        P0,
        gyro,
        accel,
        dt,
        g,
        var,
        omega,
        lever,
        pose_q,
        pose_p,
        whole=(False,) * 8 + (shared_dt, shared_g, shared_n, shared_w, shared_r) + shared_pose,
    )
    if not save_all or transition is not None:
        return out
    blocks = {k: X.reshape(X.shape[:2] + (3, 3)) for k, X in zip(UPPER, out[3 : 3 + len(UPPER)])}
    return (out[0], out[1], out[2], _blocks.blocks_to_dense(blocks)) + tuple(out[3 + len(UPPER) :])
