"""The dispatch table (jaximu/engine/_dispatch.py) against its documented copy, and
``preintegrate(method="auto")`` against the methods it chooses between."""

import pathlib
import re

import jax
import numpy as np
import pytest
from _shared import dispatch_as

import jaximu
from jaximu.engine import _dispatch

DESIGN = pathlib.Path(__file__).resolve().parents[1] / "docs" / "DESIGN.md"


def documented_table():
    text = DESIGN.read_text(encoding="utf-8")
    section = text[text.index("## 5. Dispatch"):]
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
        (entry, schemes, attitude, jac, save, lanes, max_lanes, steps, dtypes, rotating, lever,
         backends, kernel) = cells
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
        p.read_text(encoding="utf-8") for p in (root / "jaximu").rglob("*.py"))


@pytest.mark.parametrize("B,T,backend,expect", [
    (2, 160, "cpu", "parallel"), (3, 40, "cpu", "sequential"),
    # an accelerator's block holds every lane: 40 windows are few there
    (40, 100, "accelerator", "parallel")])
def test_auto_method_equals_both_methods(B, T, backend, expect):
    rng = np.random.default_rng(7)
    gyro = rng.normal(size=(B, T, 3))
    accel = rng.normal(size=(B, T, 3)) + [0, 0, 9.81]
    dt = rng.uniform(0.004, 0.006, size=(B, T))
    bias = jaximu.ImuBias(np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.0, -0.05]))
    noise = jaximu.ImuNoise.euroc()
    with dispatch_as(backend):
        assert _dispatch.preint_method("auto", B, T, np.float64) == expect
        out = {m: jaximu.preintegrate(gyro, accel, dt, bias, noise, method=m)
               for m in ("auto", "sequential", "parallel")}
    for m in ("sequential", "parallel"):
        for a, b in zip(jax.tree_util.tree_leaves(out["auto"]), jax.tree_util.tree_leaves(out[m])):
            scale = max(1.0, float(np.abs(b).max()))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * scale)
