"""``jaximu.so3``: the import path of :mod:`jaximu.geometry.so3`, where the module lives."""

from jaximu.geometry import so3 as _home
from jaximu.geometry.so3 import *  # noqa: F403
from jaximu.geometry.so3 import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
