"""Child process of ``tests/kernels/test_devices.py``: two CPU devices (``jax_num_cpu_devices`` must
be set before JAX starts, so this runs apart from the suite's process).

Each check compares a call under ``jax.set_mesh`` (lanes split over the two devices by
``jaximu.kernels.soa.run_blocked``) with the same call, in this process, without a mesh: the
reference is the single-device kernel, which the rest of the suite tests against the generic
kernels and the peers. Values and gradients must agree to 1e-12 of their scale (float64;
the kernels are elementwise in lanes, so the split changes at most the code generated for a
different lane count), and the lowered program must hold the split (one
``sdy.manual_computation``) exactly when the mesh divides the lanes, for ``Auto`` and
``Explicit`` meshes and for arrays sharded on either with no mesh set.
Prints ``OK <name>`` per check; any failure raises.
"""

import jax

jax.config.update("jax_num_cpu_devices", 2)
jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import AxisType  # noqa: E402

import jaximu  # noqa: E402

T, DT = 7, 0.01
P0 = jnp.asarray(np.diag(np.linspace(1e-4, 1e-2, 15)))
EARTH = jnp.array([0.0, 4.9e-5, 5.4e-5])  # rad/s, a rotating world
LEVER = jaximu.SensorPose(jnp.array([0.96, 0.0, 0.28, 0.0]), jnp.array([0.1, -0.2, 0.3]))


def inputs(B, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(B, 4))
    state = jaximu.NavState(
        jnp.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True)),
        *(jnp.asarray(0.1 * rng.normal(size=(B, 3))) for _ in range(4)),
    )
    gyro = jnp.asarray(rng.normal(size=(B, T + 1, 3)))
    accel = jnp.asarray(rng.normal(size=(B, T + 1, 3)) + [0.0, 0.0, 9.81])
    return state, gyro, accel


def noise(s):
    return jaximu.ImuNoise(2e-3 * s, 3e-2, 1e-4, 2e-3)


# name -> f(state, gyro, accel, s): s scales dt and a noise density (a shared value every
# lane reads: its gradient sums over the devices)
CASES = {
    "propagate_final/euler": lambda st, w, a, s: jaximu.propagate_final(
        st, w[:, :T], a[:, :T], DT * s
    ),
    "propagate/midpoint": lambda st, w, a, s: jaximu.propagate(st, w, a, DT * s, "midpoint"),
    "vmap propagate_final/rk4": lambda st, w, a, s: jax.vmap(
        lambda x, w1, a1: jaximu.propagate_final(x, w1, a1, DT * s, "rk4")
    )(st, w, a),
    "propagate_covariance_final/rk4": lambda st, w, a, s: jaximu.propagate_covariance_final(
        st, P0, w, a, DT * s, noise(s), "rk4"
    ),
    "propagate_covariance_final/euler autodiff, rotating, lever arm": lambda st, w, a, s: (
        jaximu.propagate_covariance_final(
            st,
            P0,
            w[:, :T],
            a[:, :T],
            DT * s,
            noise(s),
            jacobians="autodiff",
            omega_coriolis=EARTH,
            body_P_sensor=LEVER,
        )
    ),
    "preintegrate/euler": lambda st, w, a, s: jaximu.preintegrate(
        w[:, :T], a[:, :T], DT * s, st.bias, noise(s)
    ),
    "preintegrate/midpoint": lambda st, w, a, s: jaximu.preintegrate(
        w, a, DT * s, st.bias, noise(s), "midpoint"
    ),
}
# Gradients under the mesh: the shard_map's transpose and the cross-device sum of the shared
# scalar are run_blocked's, the same for every kernel, checked here on propagate_final.
# (preintegrate/euler passes too, and adds 23 s to this child on the 2-core host: kept out
# for the suite's time; preintegration gradients are checked against the generic kernel in
# tests/kernels/test_fast_preintegration.py.)
GRADIENTS = {"propagate_final/euler"}


def scalar(f):
    def loss(st, w, a, s):
        return sum(
            jnp.sum(jnp.sin(x))
            for x in jax.tree_util.tree_leaves(f(st, w, a, s))
            if jnp.issubdtype(x.dtype, jnp.floating)
        )

    return loss


def close(name, got, want):
    for x, y in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        scale = max(np.max(np.abs(y)), np.finfo(y.dtype).tiny)
        err = np.max(np.abs(x - y)) / scale
        assert err <= 1e-12, f"{name}: relative difference {err:.3g} under the mesh"


def run(f, args):
    """``jax.jit(f)(*args)`` and the number of lane splits in its lowered program."""
    lowered = jax.jit(f).lower(*args)
    return lowered.compile()(*args), lowered.as_text().count("sdy.manual_computation")


def check(mesh, B, names, expect_split):
    st, w, a = inputs(B)
    for name in names:
        f = CASES[name]
        args = (st, w, a, 1.0)
        want = jax.jit(f)(*args)
        grad = jax.jit(jax.grad(scalar(f), argnums=(1, 3)))
        want_g = grad(*args) if expect_split and name in GRADIENTS else None
        with jax.set_mesh(mesh):
            got, n = run(f, args)
            assert n == int(expect_split), f"{name}: {n} lane splits in the program"
            close(name, got, want)
            if want_g is not None:
                close(name + " (gradient)", grad(*args), want_g)
        print(f"OK {name} B={B} {mesh.axis_types[0]}", flush=True)


auto = jax.make_mesh((2,), ("lanes",), axis_types=(AxisType.Auto,))
check(auto, 32, list(CASES), True)  # the fast kernels' smallest batch, split 16 + 16
# an odd batch is not split (the driver's rule, the same for every kernel): the same results
check(auto, 33, ["propagate_final/euler", "preintegrate/euler"], False)
# an Explicit mesh (sharding in types): split too, the results gathered back to replicated
explicit = jax.make_mesh((2,), ("lanes",), axis_types=(AxisType.Explicit,))
check(explicit, 32, ["propagate_covariance_final/rk4", "preintegrate/midpoint"], True)
# arrays sharded on a mesh, no mesh set: their types carry the mesh. Which mesh the lanes
# split over is run_blocked's reading (jaximu.kernels.soa._mesh_axes), the same for every
# kernel, so the cheapest program to compile checks it: the mean with every state (outputs
# with a time axis, gathered back), whose single-device result is compiled above already.
# (propagate_covariance_final/rk4 passes too; its two sharded programs cost 4 s of CPU.)
st, w, a = inputs(32)
f = CASES["propagate/midpoint"]
want = jax.jit(f)(st, w, a, 1.0)
for mesh in (auto, explicit):
    split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("lanes"))
    got, n = run(f, jax.device_put((st, w, a), split) + (1.0,))
    assert n == 1, f"{n} lane splits with inputs sharded on an {mesh.axis_types[0]} mesh"
    close(f"inputs sharded on an {mesh.axis_types[0]} mesh", got, want)
    print(f"OK inputs sharded on an {mesh.axis_types[0]} mesh, no mesh set", flush=True)
# one sequence whose time axis a user split over the devices: nothing to split into lanes, so
# the kernel runs whole, and must see its inputs gathered (collectives inside the one-kernel
# call cannot be linked by XLA:CPU; slicing a sharded time axis fails under an Explicit
# mesh). Placed on either mesh, with and without the mesh set; the same results.
Tn = 64  # divisible by the 2 devices
st1 = jax.tree_util.tree_map(lambda x: x[0], inputs(1)[0])
rng = np.random.default_rng(3)
w1 = jnp.asarray(rng.normal(size=(Tn, 3)))
a1 = jnp.asarray(rng.normal(size=(Tn, 3)) + [0.0, 0.0, 9.81])
ONE = {
    "preintegrate/euler sequential": lambda w, a: jaximu.preintegrate(
        w, a, DT, st1.bias, noise(1.0), method="sequential"
    ),
    "propagate_covariance/midpoint": lambda w, a: jaximu.propagate_covariance(
        st1, P0, w, a, DT, noise(1.0), "midpoint"
    ),
}
for name, f in ONE.items():
    want = jax.jit(f)(w1, a1)
    for mesh, set_mesh in ((auto, True), (explicit, False)):
        time_split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("lanes"))
        args = jax.device_put((w1, a1), time_split)
        if set_mesh:
            with jax.set_mesh(mesh):
                got = jax.jit(f)(*args)
        else:
            got = jax.jit(f)(*args)
        close(f"{name}, time axis split", got, want)
        print(f"OK {name}, time axis split on an {mesh.axis_types[0]} mesh", flush=True)
