"""``jaximu.datasets``: the import path of :mod:`jaximu.io.datasets`, where the module lives."""

from jaximu.io import datasets as _home
from jaximu.io.datasets import *  # noqa: F403
from jaximu.io.datasets import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
