"""The README is the front page, and its Quickstart's test command is the one CI runs.

The documentation site itself (every page of the nav present, every link and anchor
resolved, every docstring parsed) is checked by ``mkdocs build --strict`` in ``.ci/run``."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def quickstart_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Quickstart") :]
    block = re.search(r"```bash\n(.*?)```", section, re.DOTALL).group(1)
    return [line.split("#")[0].strip() for line in block.splitlines() if line.strip()]


def test_the_readme_test_command_is_the_one_ci_runs():
    commands = quickstart_commands()
    assert len(commands) == 2, "the Quickstart has two set-up lines: the demo and the tests"
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert commands[1] in ci, f"{commands[1]!r} is not a line of .ci/run"


def test_the_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 300, "the guide's pages are under docs/guide/"
