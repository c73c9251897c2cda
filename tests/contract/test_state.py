"""The state constructors name a bad ``batch_shape`` (with the fix for an int)."""

from __future__ import annotations

import pytest

import jaximu


@pytest.mark.parametrize("make", [jaximu.NavState.identity, jaximu.ImuBias.zeros])
def test_constructors_name_a_bad_batch_shape(make):
    """An int batch_shape raised Python's "'int' object is not iterable"; a negative or
    non-int dimension JAX's shape error. Both are named, with the fix for the int."""
    with pytest.raises(
        ValueError,
        match=r"batch_shape must be a tuple of ints, got the int 3; "
        r"pass batch_shape=\(3,\)",
    ):
        make(3)
    with pytest.raises(ValueError, match=r"batch_shape must be a tuple of non-negative ints"):
        make((2, -1))
    assert make((2,)).b_g.shape == (2, 3)
