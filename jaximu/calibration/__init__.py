"""Calibration of an IMU against a reference trajectory: the problem (:mod:`.problem`), its
frame and time checks (:mod:`._checks`), the sensor model (:mod:`._model`), the fit
(:mod:`._fit`), the noise densities' fit (:mod:`._noise_fit`, :mod:`._noise_table`) and Kalibr's
files (:mod:`.kalibr`). ``jaximu.calibration`` is the public path of :mod:`.problem`'s API.
Imports the engine, :mod:`jaximu.io` and below.
"""

from jaximu.calibration import problem as _problem
from jaximu.calibration.problem import *  # noqa: F403
from jaximu.calibration.problem import __all__ as __all__


def __getattr__(name):
    """The other names of the module ``jaximu.calibration`` was before it was a folder
    (helpers, the modules it imported), for code that reaches them here."""
    return getattr(_problem, name)
