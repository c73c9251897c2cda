"""``jaximu learn evaluate`` checks every sequence and the model before the first table: a
bad one among several prints no table and writes nothing, and a model whose weights hold a
NaN (a diverged training) is refused when it loads, naming its weights file."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from test_learning_commands import TINY, run, write_sequence

from jaximu import learning
from jaximu.learning import Denoiser


def test_a_sequence_too_short_for_the_tracker_is_refused_before_any_table(capsys, tmp_path):
    """A (5 s) evaluates; B's ground truth covers 8 IMU samples, fewer than the 10 the
    shipped model's tracker levels on: nothing of A is printed, and no JSON is written."""
    a = write_sequence(tmp_path / "A", seconds=5.0)
    b = write_sequence(tmp_path / "B", seconds=5.0, seed=1)
    gt = b / "groundtruth.csv"
    gt.write_text("\n".join(gt.read_text().splitlines()[:9]) + "\n")
    js = tmp_path / "out.json"
    code, out, err = run(capsys, "learn", "evaluate", "euroc", str(a), str(b), "--json", str(js))
    assert code == 2, (out, err)
    assert "'B'" in err and "8 IMU samples" in err and "at least 10" in err
    assert "AOE mean" not in out and "average" not in out
    assert not js.exists()


def test_a_model_with_a_nan_weight_is_refused_when_it_loads(capsys, tmp_path):
    model = Denoiser(TINY, jax.random.key(0))
    folder = learning.save(tmp_path / "model", model)
    bad = eqx.tree_at(lambda m: m.head.bias, model, jnp.full_like(model.head.bias, jnp.nan))
    eqx.tree_serialise_leaves(
        folder / "weights.eqx", learning.checkpoint.weights(bad)
    )  # as a diverged training left it
    seq = write_sequence(tmp_path / "seq", seconds=2.0)
    code, out, err = run(capsys, "learn", "evaluate", str(folder), str(seq))
    assert code == 2, (out, err)
    assert "weights.eqx" in err and "non-finite" in err and "model.head.bias[0]" in err
    assert "AOE mean" not in out
