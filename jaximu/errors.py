"""Errors that carry their repair as data.

An :class:`InputError` (a ``ValueError``) holds the problem in words and the repairs as
:class:`Fix` values, each an option of the function that raised it and the value that fixes
the input. Its message renders the repairs as keyword arguments (``pass gyro_unit='deg/s'``);
the ``jaximu`` command renders the same repairs as its flags (``pass --gyro-unit deg/s``)
with :meth:`InputError.render`, so neither depends on the other's wording.

    try:
        data = jaximu.io.read_csv("imu.csv")
    except jaximu.errors.InputError as e:
        print(e.problem, e.fixes)   # (Fix(option='gyro_unit', value='deg/s'), ...)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

__all__ = ["ANY", "Fix", "InputError"]


class _Any:
    def __repr__(self):
        return "ANY"


ANY: Any = _Any()
"""A :class:`Fix` value meaning "another value" (described by the fix's ``phrase``)."""


@dataclasses.dataclass(frozen=True)
class Fix:
    """One repair: pass ``option=value``.

    Attributes:
        option: the keyword argument of the function that raised (``"gyro_unit"``).
        value: the value that repairs the input (``"deg/s"``, ``True``), or :data:`ANY` when
            the right value is the user's to choose (``phrase`` then says how: ``"a larger"``).
        phrase: when ``value`` is :data:`ANY`, the words around the option: ``"a larger"``
            (the option follows) or ``"check the time unit ({})"`` (it replaces ``{}``).
    """

    option: str
    value: Any = ANY
    phrase: str = ""

    def as_keyword(self) -> str:
        """``option='value'`` (or ``phrase option``), as a Python call would take it."""
        if self.value is ANY:
            return self.describe(self.option)
        return f"{self.option}={self.value!r}"

    def describe(self, name: str) -> str:
        """The ``phrase`` with ``name`` (the option, or the command's flag) in its ``{}``,
        or after it."""
        if "{}" in self.phrase:
            return self.phrase.format(name)
        return f"{self.phrase} {name}".strip()


class InputError(ValueError):
    """Bad input, with the repairs as data.

    Attributes:
        problem: what is wrong, in words, naming the user's input.
        fixes: the :class:`Fix` values, any one of which repairs it (may be empty).
        lead: the words before the fixes (``"pass"``).
        api_note: advice that holds only for the Python API (not rendered by the command).
    """

    def __init__(
        self, problem: str, fixes=(), *, lead: str = "pass", sep: str = "; ", api_note: str = ""
    ):
        self.problem = problem
        self.fixes = tuple(fixes)
        self.lead = lead
        self.sep = sep
        self.api_note = api_note
        super().__init__(self.render())

    def render(self, option: Callable[[Fix], str] | None = None) -> str:
        """The message with each fix rendered by ``option`` (default: as a keyword argument,
        with the API-only note)."""
        if not self.fixes:
            return self.problem
        words = [(option or Fix.as_keyword)(f) for f in self.fixes]
        note = self.api_note if option is None else ""
        lead = f"{self.lead} " if self.lead else ""
        return f"{self.problem}{self.sep}{lead}{' or '.join(words)}{note}"

    def __reduce__(self):  # pickling (multiprocessing, pytest-xdist) keeps the data
        return (
            _rebuild,
            (type(self), self.problem, self.fixes, self.lead, self.sep, self.api_note),
        )


def _rebuild(cls, problem, fixes, lead, sep, api_note):
    return cls(problem, fixes, lead=lead, sep=sep, api_note=api_note)
