"""jaximu: a differentiable, batched IMU propagation engine in JAX.

Conventions (see README): Hamilton ``[w, x, y, z]`` quaternion of ``R_WB``; world z up,
``g_W = [0, 0, -g]``; specific-force accelerometer; error state ``[dθ, dp, dv, db_g, db_a]``
with the rotation error on the right; Kalibr noise densities.
"""

from jaximu import allan as allan
from jaximu import errors as errors
from jaximu import errorstate as errorstate
from jaximu import integrators as integrators
from jaximu import io as io
from jaximu import montecarlo as montecarlo
from jaximu import noise as noise
from jaximu import preintegration as preintegration

# the module jaximu.propagate is loaded before the name is bound to the function, as it was
# when the module lived here (a later ``import jaximu.propagate`` then leaves the name alone)
from jaximu import propagate as _propagate_module  # noqa: F401
from jaximu import sensor as sensor
from jaximu import simulate as simulate
from jaximu import so3 as so3
from jaximu import state as state
from jaximu import world as world
from jaximu.engine.errorstate import propagate_covariance as propagate_covariance
from jaximu.engine.errorstate import propagate_covariance_final as propagate_covariance_final
from jaximu.engine.jacobians import discrete_process_noise as discrete_process_noise
from jaximu.engine.jacobians import step_jacobians as step_jacobians
from jaximu.engine.preintegration import Preintegrated as Preintegrated
from jaximu.engine.preintegration import bias_jacobians_autodiff as bias_jacobians_autodiff
from jaximu.engine.preintegration import compose as compose
from jaximu.engine.preintegration import correct as correct
from jaximu.engine.preintegration import needs_reintegration as needs_reintegration
from jaximu.engine.preintegration import predict as predict
from jaximu.engine.preintegration import preintegrate as preintegrate
from jaximu.engine.preintegration import residual as residual
from jaximu.engine.preintegration import whitened_residual as whitened_residual
from jaximu.engine.propagate import propagate as propagate
from jaximu.engine.propagate import propagate_final as propagate_final
from jaximu.engine.update import ekf_update as ekf_update
from jaximu.geometry.noise import ImuNoise as ImuNoise
from jaximu.geometry.sensor import SensorPose as SensorPose
from jaximu.geometry.state import ImuBias as ImuBias
from jaximu.geometry.state import NavState as NavState
from jaximu.geometry.state import boxminus as boxminus
from jaximu.geometry.state import boxplus as boxplus
from jaximu.schemes.integrators import ATTITUDES as ATTITUDES
from jaximu.schemes.integrators import SCHEMES as SCHEMES
from jaximu.schemes.world import earth_rate as earth_rate

__version__ = "0.1.0"
