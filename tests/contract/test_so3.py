"""The ``jaximu.so3`` kernels' input contract: every kernel checks the trailing shape of each
argument and names it (a hypothesis property over all kernels and arguments), batches that
do not broadcast are named, and Python lists and integers are taken as float rotations
(scipy is the reference).
"""

from __future__ import annotations

import re

import jax.numpy as jnp
import numpy as np
import pytest
from _shared import fast_settings
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jaximu import so3

# every so3 kernel: (function, [(argument name, last-axis shape), ...])
SO3_SIGNATURES = {
    "skew": [("v", (3,))],
    "quat_mul": [("p", (4,)), ("q", (4,))],
    "quat_conj": [("q", (4,))],
    "quat_normalize": [("q", (4,))],
    "quat_rotate": [("q", (4,)), ("v", (3,))],
    "quat_to_matrix": [("q", (4,))],
    "matrix_to_quat": [("R", (3, 3))],
    "exp": [("phi", (3,))],
    "log": [("q", (4,))],
    "exp_matrix": [("phi", (3,))],
    "log_matrix": [("R", (3, 3))],
    "right_jacobian": [("phi", (3,))],
    "right_jacobian_inv": [("phi", (3,))],
    "left_jacobian": [("phi", (3,))],
    "quat_first_order_update": [("q", (4,)), ("phi", (3,))],
    "xyzw_to_wxyz": [("q", (4,))],
    "wxyz_to_xyzw": [("q", (4,))],
    "jpl_to_hamilton": [("q_jpl", (4,))],
    "hamilton_to_jpl": [("q_wb", (4,))],
    "euler_zyx_to_quat": [("chi", (3,))],
    "euler_zyx_to_matrix": [("chi", (3,))],
    "quat_to_euler_zyx": [("q", (4,))],
    "euler_rate_matrix": [("chi", (3,))],
}


def test_every_so3_kernel_is_in_the_signature_table():
    assert set(SO3_SIGNATURES) == set(so3.__all__) - {"quat_identity"}


def test_so3_reported_examples_raise_naming_the_argument():
    with pytest.raises(
        ValueError, match=r"so3\.exp: phi must have shape \(\.\.\., 3\), got \(4,\)"
    ):
        so3.exp(np.zeros(4))
    with pytest.raises(
        ValueError,
        match=r"so3\.quat_to_matrix: q must have shape \(\.\.\., 4\), "
        r"got \(3,\)",
    ):
        so3.quat_to_matrix(np.zeros(3))
    with pytest.raises(ValueError, match=r"so3\.log_matrix: R must have shape \(\.\.\., 3, 3\)"):
        so3.log_matrix(np.eye(4))


def test_so3_batches_that_do_not_broadcast_are_named():
    with pytest.raises(
        ValueError,
        match=r"so3\.quat_rotate: the batch shapes of q \(2, 4\) "
        r"and v \(3, 3\) do not broadcast",
    ):
        so3.quat_rotate(np.ones((2, 4)), np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"so3\.quat_mul: the batch shapes of p"):
        so3.quat_mul(np.ones((2, 4)), np.ones((5, 4)))


def test_so3_accepts_python_lists_like_arrays():
    """A ROS quaternion as a list: the same numbers as scipy's."""
    q_xyzw = [0.1, -0.2, 0.3, 0.9273618495495704]  # unit
    q = so3.xyzw_to_wxyz(q_xyzw)
    np.testing.assert_allclose(np.asarray(q), np.r_[q_xyzw[3], q_xyzw[:3]], rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(so3.quat_to_matrix(list(np.asarray(q)))),
        Rotation.from_quat(q_xyzw).as_matrix(),
        atol=1e-6,
    )
    np.testing.assert_allclose(
        np.asarray(so3.exp([0.0, 0.0, np.pi / 2])), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-6
    )
    np.testing.assert_allclose(np.asarray(so3.quat_rotate([1, 0, 0, 0], [1, 2, 3])), [1, 2, 3])


@fast_settings(60)
@given(st.data())
def test_so3_kernels_refuse_wrong_shapes_naming_the_argument(data):
    """Any kernel, any of its arguments given a wrong trailing shape (or a scalar): a
    ``ValueError`` naming the function, the argument and the shape wanted."""
    name = data.draw(st.sampled_from(sorted(SO3_SIGNATURES)), label="kernel")
    sig = SO3_SIGNATURES[name]
    bad = data.draw(st.integers(0, len(sig) - 1), label="argument")
    batch = data.draw(st.sampled_from(((), (2,))), label="batch")
    args = []
    for i, (_arg, shape) in enumerate(sig):
        if i == bad:
            # wrong: not ending in the shape wanted ((2, 4) is a batch of quaternions)
            shape = data.draw(
                st.sampled_from(
                    [
                        s
                        for s in ((), (2,), (3,), (4,), (5,), (3, 3), (4, 4), (3, 4), (4, 3))
                        if s[len(s) - len(shape) :] != shape
                    ]
                ),
                label="wrong shape",
            )
            args.append(np.ones(batch + shape if shape else ()))
        else:
            args.append(np.ones(batch + shape))
    want = ", ".join(str(s) for s in sig[bad][1])
    with pytest.raises(ValueError) as err:
        getattr(so3, name)(*args)
    assert re.search(
        rf"so3\.{name}: {sig[bad][0]} must have shape \(\.\.\., {want}\)", str(err.value)
    ), str(err.value)


def test_so3_of_integer_lists_is_computed_in_floats():
    """A ROS-style quaternion typed as integers is a rotation, not integer arithmetic."""
    q = so3.quat_mul([1, 0, 0, 0], [0, 1, 0, 0])
    assert jnp.issubdtype(q.dtype, jnp.floating)
    np.testing.assert_allclose(q, [0, 1, 0, 0])
    R = so3.quat_to_matrix([0, 0, 0, 1])  # 180° about z
    np.testing.assert_allclose(R, Rotation.from_quat([0, 0, 1, 0]).as_matrix(), atol=1e-6)
    np.testing.assert_allclose(so3.exp([0, 0, 0]), [1, 0, 0, 0])
