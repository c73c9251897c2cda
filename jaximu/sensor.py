"""``jaximu.sensor``: the import path of :mod:`jaximu.geometry.sensor`, where the module lives."""

from jaximu.geometry import sensor as _home
from jaximu.geometry.sensor import *  # noqa: F403
from jaximu.geometry.sensor import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
