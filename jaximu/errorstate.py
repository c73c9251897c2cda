"""``jaximu.errorstate``: the import path of :mod:`jaximu.engine.errorstate`, where the module lives."""

from jaximu.engine import errorstate as _home
from jaximu.engine.errorstate import *  # noqa: F403
from jaximu.engine.errorstate import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
