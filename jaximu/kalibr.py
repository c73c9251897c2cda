"""``jaximu.kalibr``: the import path of :mod:`jaximu.calibration.kalibr`, where the module lives."""

from jaximu.calibration.kalibr import *  # noqa: F403
from jaximu.calibration.kalibr import __all__ as __all__
