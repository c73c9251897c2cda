"""``docs/accepts.md`` ("what each function accepts") cannot drift from the code: every public
function of the package and of its public modules has a section, each section lists exactly
the function's parameters, and the command's options part equals what the parser generates."""

from __future__ import annotations

import inspect
import pathlib
import re

import pytest

import jaximu
from jaximu import (
    allan,
    calibration,
    cli,
    io,
    keyframes,
    learning,
    montecarlo,
    recording,
    simulate,
    so3,
)

DOC = pathlib.Path(__file__).parent.parent / "docs" / "accepts.md"
MODULES = {
    "jaximu": jaximu,
    "jaximu.so3": so3,
    "jaximu.allan": allan,
    "jaximu.montecarlo": montecarlo,
    "jaximu.calibration": calibration,
    "jaximu.io": io,
    "jaximu.simulate": simulate,
    "jaximu.recording": recording,
    "jaximu.keyframes": keyframes,
    "jaximu.learning": learning,
}


def public_functions():
    out = {}
    for prefix, mod in MODULES.items():
        names = (
            getattr(mod, "__all__", None)
            if mod is not jaximu
            else [n for n in dir(mod) if not n.startswith("_")]
        )
        for name in names:
            f = getattr(mod, name)
            if inspect.isfunction(f):
                out[f"{prefix}.{name}"] = [p for p in inspect.signature(f).parameters]
    return out


def documented():
    text = DOC.read_text().split("# The command's options")[0]
    table, current = {}, None
    for line in text.splitlines():
        m = re.match(r"## `([\w.]+)`$", line)
        if m:
            current = table.setdefault(m.group(1), [])
            continue
        m = re.match(r"\| `(\w+)` \|", line)
        if m and current is not None:
            current.append(m.group(1))
    return table


FUNCTIONS = public_functions()


def test_the_table_has_every_public_function_and_no_other():
    doc = documented()
    assert len(FUNCTIONS) > 60
    assert sorted(set(FUNCTIONS) - set(doc)) == [], "public functions missing from docs/accepts.md"
    assert sorted(set(doc) - set(FUNCTIONS)) == [], "docs/accepts.md names functions that are gone"


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_each_section_lists_exactly_the_parameters(name):
    rows = documented().get(name, [])
    assert len(rows) == len(set(rows)), f"{name}: a parameter is listed twice"
    assert set(rows) == set(FUNCTIONS[name]), (
        f"{name}: missing {set(FUNCTIONS[name]) - set(rows)}, stale {set(rows) - set(FUNCTIONS[name])}"
    )


def test_the_command_options_part_is_generated_from_the_parser():
    text = DOC.read_text()
    part = text.split("<!-- options begin -->\n")[1].split("<!-- options end -->")[0]
    assert part == cli.options_table(), "regenerate: jaximu.cli.options_table()"
