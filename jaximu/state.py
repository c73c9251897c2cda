"""``jaximu.state``: the import path of :mod:`jaximu.geometry.state`, where the module lives."""

from jaximu.geometry import state as _home
from jaximu.geometry.state import *  # noqa: F403
from jaximu.geometry.state import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
