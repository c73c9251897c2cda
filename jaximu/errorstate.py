"""``jaximu.errorstate``: the import path of the error-state functions, which live in
:mod:`jaximu.engine.errorstate` (covariance propagation), :mod:`jaximu.engine.jacobians` (the
step's ``Φ``, ``G`` and ``Q_d``) and :mod:`jaximu.engine.update` (the filter update)."""

from jaximu.engine import errorstate as _covariance
from jaximu.engine import jacobians as _jacobians
from jaximu.engine import update as _update
from jaximu.engine.errorstate import (
    accumulate_covariance,
    compose_transitions,
    propagate_covariance,
    propagate_covariance_final,
    transition_products,
)
from jaximu.engine.jacobians import JACOBIANS, discrete_process_noise, step_jacobians
from jaximu.engine.update import ekf_update, position_jacobian

__all__ = [
    "step_jacobians",
    "discrete_process_noise",
    "propagate_covariance",
    "propagate_covariance_final",
    "accumulate_covariance",
    "compose_transitions",
    "transition_products",
    "ekf_update",
    "position_jacobian",
    "JACOBIANS",
]


def __getattr__(name):
    """The modules' other names (those outside ``__all__``), for code that reaches them here."""
    for home in (_covariance, _jacobians, _update):
        if hasattr(home, name):
            return getattr(home, name)
    raise AttributeError(f"module 'jaximu.errorstate' has no attribute {name!r}")
