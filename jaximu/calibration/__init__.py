"""Calibration of an IMU against a reference trajectory: the problem (:mod:`.problem`), its
estimate (:mod:`._estimate`), the frame and time checks (:mod:`._checks`), the sensor model
(:mod:`._model`), the fit (:mod:`._fit`), the noise densities' fit (:mod:`._noise_problem`,
:mod:`._noise_fit`, :mod:`._noise_filter`, :mod:`._noise_table`) and Kalibr's files
(:mod:`.kalibr`). ``jaximu.calibration`` is the public path of the problem's and the
estimate's API. Imports the engine, :mod:`jaximu.io` and below.
"""

from jaximu.calibration import _estimate, problem
from jaximu.calibration._estimate import CalibrationResult, calibrate
from jaximu.calibration.problem import (
    FIELDS,
    NOISE_FIELDS,
    PER_AXIS_FIELDS,
    SCALES,
    CalibrationError,
    CalibrationProblem,
    ImuCalibration,
    Reference,
    calibration_loss,
    calibration_problem,
    calibration_residuals,
    noise_table,
)

__all__ = [
    "ImuCalibration",
    "Reference",
    "CalibrationProblem",
    "CalibrationResult",
    "CalibrationError",
    "calibration_problem",
    "calibration_loss",
    "calibration_residuals",
    "calibrate",
    "FIELDS",
    "NOISE_FIELDS",
    "PER_AXIS_FIELDS",
    "SCALES",
    "noise_table",
]


def __getattr__(name):
    """The other names of the module ``jaximu.calibration`` was before it was a folder
    (helpers, the modules it imported), for code that reaches them here."""
    for home in (problem, _estimate):
        if hasattr(home, name):
            return getattr(home, name)
    raise AttributeError(f"module 'jaximu.calibration' has no attribute {name!r}")
