"""``jaximu.propagate``: the import path of :mod:`jaximu.engine.propagate`, where the module
lives (its input preparation in :mod:`jaximu.engine._inputs`)."""

from jaximu.engine import _inputs
from jaximu.engine import propagate as _home
from jaximu.engine.propagate import *  # noqa: F403
from jaximu.engine.propagate import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home if hasattr(_home, name) else _inputs, name)
