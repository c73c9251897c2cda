"""``jaximu.noise``: the import path of :mod:`jaximu.geometry.noise`, where the module lives."""

from jaximu.geometry import noise as _home
from jaximu.geometry.noise import *  # noqa: F403
from jaximu.geometry.noise import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
