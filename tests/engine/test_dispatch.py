"""The dispatch table (jaximu/engine/_dispatch.py) against its documented copy, and
``preintegrate(method="auto")`` against the methods it chooses between."""

import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import dispatch_as, random_inputs

import jaximu
from jaximu.engine import _dispatch

DESIGN = pathlib.Path(__file__).resolve().parents[2] / "docs" / "DESIGN.md"


def documented_table():
    text = DESIGN.read_text(encoding="utf-8")
    section = text[text.index("## 5. Dispatch") :]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 13 and cells[0] in ("mean", "covariance", "preintegrate"):
            rows.append(cells)
    return rows


def test_design_notes_table_is_the_code_table():
    def words(x):
        return () if x in ("–", "-") else tuple(w.strip() for w in x.split(","))

    doc = documented_table()
    assert len(doc) == len(_dispatch.TABLE)
    stored = {"final": False, "all": True}
    for cells, row in zip(doc, _dispatch.TABLE):
        (
            entry,
            schemes,
            attitude,
            jac,
            save,
            lanes,
            max_lanes,
            steps,
            dtypes,
            rotating,
            lever,
            backends,
            kernel,
        ) = cells
        assert entry == row.entry
        assert words(schemes) == row.schemes
        assert words(attitude) == (row.attitudes or ())
        assert words(jac) == (row.jacobians or ())
        assert tuple(stored[s] for s in words(save)) == row.save_all
        assert int(lanes) == row.min_lanes
        assert (None if max_lanes in ("–", "-") else int(max_lanes)) == row.max_lanes
        assert int(steps) == row.min_steps
        assert words(dtypes) == row.dtypes
        assert tuple({"no": False, "yes": True}[w] for w in words(rotating)) == row.rotating
        assert tuple({"no": False, "yes": True}[w] for w in words(lever)) == (row.lever or ())
        assert words(backends) == row.backends
        assert kernel == row.kernel


def test_every_citation_of_the_design_notes_points_at_the_file():
    root = DESIGN.parents[1]
    for path in list((root / "jaximu").rglob("*.py")):
        for m in re.finditer(r"(\S*)DESIGN\.md", path.read_text(encoding="utf-8")):
            assert m.group(1).endswith("docs/"), f"{path.name} cites {m.group(0)!r}"
    assert "perf report" not in "".join(
        p.read_text(encoding="utf-8") for p in (root / "jaximu").rglob("*.py")
    )


@pytest.mark.parametrize(
    "B,T,backend,expect",
    [
        (2, 160, "cpu", "parallel"),
        (3, 40, "cpu", "sequential"),
        # an accelerator's block holds every lane: 40 windows are few there
        (40, 100, "accelerator", "parallel"),
    ],
)
def test_auto_method_equals_both_methods(B, T, backend, expect):
    rng = np.random.default_rng(7)
    gyro = rng.normal(size=(B, T, 3))
    accel = rng.normal(size=(B, T, 3)) + [0, 0, 9.81]
    dt = rng.uniform(0.004, 0.006, size=(B, T))
    bias = jaximu.ImuBias(np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.0, -0.05]))
    noise = jaximu.ImuNoise.euroc()
    with dispatch_as(backend):
        assert _dispatch.preint_method("auto", B, T, np.float64) == expect
        out = {
            m: jaximu.preintegrate(gyro, accel, dt, bias, noise, method=m)
            for m in ("auto", "sequential", "parallel")
        }
    for m in ("sequential", "parallel"):
        for a, b in zip(jax.tree_util.tree_leaves(out["auto"]), jax.tree_util.tree_leaves(out[m])):
            scale = max(1.0, float(np.abs(b).max()))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * scale)


class Picked(Exception):
    """The kernel the dispatch named: stops the trace there."""


def kernel_picked(entry, lanes, steps, monkeypatch, **kw):
    """The kernel the dispatch names when ``entry`` (``"mean"``: ``propagate_final``,
    ``"covariance"``: ``propagate_covariance_final``) of ``lanes`` sequences of ``steps``
    float32 samples is traced (``jax.eval_shape``, stopped at the dispatch: nothing is
    compiled or allocated)."""
    kernel = _dispatch.kernel

    def spy(*args, **kwargs):
        raise Picked(kernel(*args, **kwargs))

    monkeypatch.setattr(_dispatch, "kernel", spy)
    f32 = lambda *shape: jax.ShapeDtypeStruct(shape, np.float32)  # noqa: E731
    state = jaximu.NavState(
        f32(lanes, 4), f32(lanes, 3), f32(lanes, 3), f32(lanes, 3), f32(lanes, 3)
    )
    samples = (f32(lanes, steps, 3), f32(lanes, steps, 3), f32(steps))
    noise = jaximu.ImuNoise.euroc()
    try:
        if entry == "mean":
            jax.eval_shape(
                lambda s, g, a, d: jaximu.propagate_final(s, g, a, d, **kw), state, *samples
            )
        else:
            jax.eval_shape(
                lambda s, P, g, a, d: jaximu.propagate_covariance_final(s, P, g, a, d, noise, **kw),
                state,
                f32(15, 15),
                *samples,
            )
    except Picked as picked:
        return picked.args[0]
    finally:
        monkeypatch.undo()
    raise AssertionError("the entry did not ask the dispatch")


def test_the_table_returns_the_function_that_runs_each_kernel():
    """Every kernel the table names (and each entry's generic one) has the function that runs
    it registered by its engine module, and ``implementation`` returns that function for the
    options the row matches (the same choice :func:`kernel` names), read from the functions'
    own modules and names."""
    from jaximu.engine import _covariance_lanes, _preintegration_engine, propagate

    registered = _dispatch._IMPLEMENTATIONS
    for row in _dispatch.TABLE:
        assert (row.entry, row.kernel) in registered, row
    for entry in ("mean", "covariance", "preintegrate"):
        assert (entry, _dispatch.GENERIC) in registered, entry
    on_cpu = dict(dtype="float64", on=_dispatch.CPU)
    mean = dict(attitude="quaternion", steps=100, **on_cpu)
    assert _dispatch.implementation("mean", "euler", lanes=64, **mean) is propagate._mean_soa
    assert (
        _dispatch.implementation("mean", "euler", lanes=64, fast=False, **mean)
        is propagate._mean_generic
    )
    cov = dict(attitude="quaternion", jacobians="analytic", **on_cpu)
    assert (
        _dispatch.implementation("covariance", "midpoint", lanes=64, steps=100, **cov)
        is _covariance_lanes.covariance_soa
    )
    assert (
        _dispatch.implementation("covariance", "euler", lanes=1, steps=4096, **cov)
        is _covariance_lanes.covariance_chunked
    )
    assert (
        _dispatch.preintegrate_implementation(
            "euler", jacobians="analytic", prefixes=True, method="sequential", lanes=64
        )
        is _preintegration_engine._preintegrate_generic
    )


def test_accelerator_takes_time_chunks_from_the_tables_thresholds(monkeypatch):
    """On an accelerator (its dispatch run here: tests/_shared.dispatch_as) the public
    entries ask the dispatch for the time chunks from the table's length (``MEAN_CHUNK_STEPS``,
    ``COV_CHUNK_STEPS``) on, up to its batch (``MEAN_CHUNK_LANES``, ``COV_CHUNK_LANES``),
    and the sequential kernels one step shorter or one sequence more; the CPU keeps the
    sequential kernels at those lengths. The results are tested against the sequential
    kernels in tests/engine/test_chunked_covariance.py and tests/kernels/test_fast_path.py."""
    acc = _dispatch.ACCELERATOR
    mean_n, mean_b = _dispatch.MEAN_CHUNK_STEPS, _dispatch.MEAN_CHUNK_LANES
    cov_n, cov_b = _dispatch.COV_CHUNK_STEPS[acc], _dispatch.COV_CHUNK_LANES[acc]
    assert _dispatch.MEAN_CHUNK_STEPS < 2048 and cov_n < _dispatch.COV_CHUNK_STEPS["cpu"]
    with dispatch_as(acc):
        for lanes, steps, expect in [
            (1, mean_n, "soa_mean_chunked"),
            (1, mean_n - 1, "generic"),
            (mean_b, mean_n, "soa_mean_chunked"),
            (mean_b + 1, mean_n, "generic"),
        ]:
            assert kernel_picked("mean", lanes, steps, monkeypatch) == expect, (lanes, steps)
        for lanes, steps, expect in [
            (1, cov_n, "soa_cov_chunked"),
            (1, cov_n - 1, "soa_cov_analytic"),
            (cov_b, cov_n, "soa_cov_chunked"),
            (cov_b + 1, cov_n, "soa_cov_analytic"),
        ]:
            assert kernel_picked("covariance", lanes, steps, monkeypatch) == expect, (lanes, steps)
        # also where the mean's own pass gives the chunks' starts (Euler angles)
        assert (
            kernel_picked(
                "covariance", 2, cov_n, monkeypatch, jacobians="autodiff", attitude="euler_angles"
            )
            == "soa_cov_chunked"
        )
    assert kernel_picked("mean", 1, mean_n, monkeypatch) == "soa_mean"
    assert kernel_picked("covariance", 1, cov_n, monkeypatch) == "soa_cov_analytic"


def test_accelerator_mean_of_short_sequences_in_time_chunks_equals_the_scan():
    """Two float64 sequences of the accelerator's threshold length (``MEAN_CHUNK_STEPS``:
    4 chunks of 32 steps each, the deltas composed as a tree; every state stored, the chunks
    run again from their starts' parallel prefix), per-sample dt, on the accelerator's
    dispatch run here: the CPU's sequential kernel's states (itself tested against the
    generic scan, tests/kernels/test_fast_path.py) to 1e-12 of the largest value."""
    n = _dispatch.MEAN_CHUNK_STEPS
    state, gyro, accel = random_inputs(2, n, seed=31)
    dt = jnp.asarray(np.random.default_rng(32).uniform(0.003, 0.007, (2, n)))

    def run(s, g, a, d):
        return (
            jaximu.propagate_final(s, g, a, d, "midpoint"),
            jaximu.propagate(s, g, a, d, "midpoint"),
        )

    with dispatch_as(_dispatch.ACCELERATOR):
        assert (
            _dispatch.kernel("mean", "midpoint", attitude="quaternion", lanes=2, steps=n)
            == "soa_mean_chunked"
        )
        assert _dispatch.mean_chunks(2, n) == 4
        chunked = jax.jit(run)(state, gyro, accel, dt)
    ref = jax.jit(run)(state, gyro, accel, dt)
    for a, b in zip(jax.tree_util.tree_leaves(chunked), jax.tree_util.tree_leaves(ref)):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))
