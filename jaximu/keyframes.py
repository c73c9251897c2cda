"""``jaximu.keyframes``: the import path of :mod:`jaximu.studies.keyframes`, where the module lives."""

from jaximu.studies import keyframes as _home
from jaximu.studies.keyframes import *  # noqa: F403
from jaximu.studies.keyframes import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
