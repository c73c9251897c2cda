"""``jaximu.allan``: the import path of :mod:`jaximu.studies.allan`, where the module lives."""

from jaximu.studies import allan as _home
from jaximu.studies.allan import *  # noqa: F403
from jaximu.studies.allan import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
