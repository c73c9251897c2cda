"""``KEY=VALUE`` command-line settings onto a settings dataclass (``TrainConfig``,
``ModelConfig``), for the learning benchmarks' ``--set`` options."""

from __future__ import annotations

import dataclasses


def replaced(defaults, settings: list[str]):
    """``(defaults with the settings, the settings as keywords)``. A value is read as the
    field's type: tuples comma-separated, booleans from 1/true/yes, a field that defaults
    to ``None`` as a number."""
    kw = {}
    for s in settings:
        key, sep, value = s.partition("=")
        if not sep or not hasattr(defaults, key):
            raise SystemExit(
                f"{s!r}: expected KEY=VALUE with KEY a field of {type(defaults).__name__}"
            )
        current = getattr(defaults, key)
        if isinstance(current, tuple):
            kw[key] = tuple(type(current[0])(v) for v in value.split(",") if v)
        elif isinstance(current, bool):
            kw[key] = value.lower() in ("1", "true", "yes")
        elif current is None:
            kw[key] = float(value)
        else:
            kw[key] = type(current)(value)
    return dataclasses.replace(defaults, **kw), kw
