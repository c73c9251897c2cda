"""``jaximu.recording``: ``propagate_recording`` and ``run_demo`` check their arguments
before the work.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, NavState


def _recording_args(**kw):
    data = jaximu.io.from_arrays(
        np.arange(5) * 0.01, np.zeros((5, 3)), np.tile([0.0, 0.0, 9.81], (5, 1))
    )
    args = dict(
        data=data,
        state0=NavState.identity(),
        P0=np.eye(15) * 1e-4,
        noise=ImuNoise.euroc(),
        scheme="midpoint",
        dtype=jnp.float32,
    )
    args.update(kw)
    return args


@pytest.mark.parametrize(
    "kw,message",
    [
        ({"scheme": "rk5"}, r"unknown scheme 'rk5'"),
        ({"chunk": 0}, r"chunk must be a positive integer, got 0"),
        ({"dtype": np.float16}, r"dtype must be a floating dtype \(float32 or float64\)"),
        ({"gravity": -9.81}, r"gravity = -9\.81 is a magnitude"),
        ({"P0": -np.eye(15)}, r"P0"),
    ],
)
def test_propagate_recording_names_its_arguments(kw, message):
    from jaximu.recording import propagate_recording

    with pytest.raises(ValueError, match=message):
        propagate_recording(**_recording_args(**kw))


def test_run_demo_checks_before_the_work(tmp_path):
    from jaximu.errors import Fix, InputError
    from jaximu.recording import run_demo

    with pytest.raises(InputError, match=r"seconds=100: the bundled excerpt holds 20 s") as err:
        run_demo(100.0, plot=None)
    assert err.value.fixes == (Fix("seconds", 20.0),)
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match=r"seconds must be positive and finite"):
            run_demo(bad, plot=None)
    with pytest.raises(ValueError, match=r"unknown scheme 'rk5'"):
        run_demo(1.0, scheme="rk5", plot=None)
    with pytest.raises(ValueError, match=r"the folder .*missing does not exist"):
        run_demo(1.0, plot=str(tmp_path / "missing" / "demo.png"))
    with pytest.raises(ValueError, match=r"is a folder"):
        run_demo(1.0, plot=str(tmp_path))
