"""``jaximu.preintegration``: the import path of :mod:`jaximu.engine.preintegration`, where the module lives."""

from jaximu.engine import preintegration as _home
from jaximu.engine.preintegration import *  # noqa: F403
from jaximu.engine.preintegration import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
