"""``jaximu.world``: the import path of :mod:`jaximu.schemes.world`, where the module lives."""

from jaximu.schemes import world as _home
from jaximu.schemes.world import *  # noqa: F403
from jaximu.schemes.world import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
