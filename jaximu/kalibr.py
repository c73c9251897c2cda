"""``jaximu.kalibr``: the import path of :mod:`jaximu.calibration.kalibr`, where the module lives."""

from jaximu.calibration import kalibr as _home
from jaximu.calibration.kalibr import *  # noqa: F403
from jaximu.calibration.kalibr import __all__ as __all__


def __getattr__(name):
    """The module's other names (those outside ``__all__``), for code that reaches them here."""
    return getattr(_home, name)
