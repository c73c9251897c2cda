"""``jaximu.plots``: the import path of :mod:`jaximu.studies.plots`, where the module lives."""

from jaximu.studies import plots as _home
from jaximu.studies.plots import *  # noqa: F403
from jaximu.studies.plots import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
