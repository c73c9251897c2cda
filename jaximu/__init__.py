"""jaximu: a differentiable, batched IMU propagation engine in JAX.

Conventions (see README): Hamilton ``[w, x, y, z]`` quaternion of ``R_WB``; world z up,
``g_W = [0, 0, -g]``; specific-force accelerometer; error state ``[dθ, dp, dv, db_g, db_a]``
with the rotation error on the right; Kalibr noise densities.
"""

from jaximu import allan as allan
from jaximu import errors as errors
from jaximu import io as io
from jaximu import montecarlo as montecarlo
from jaximu import sensor as sensor
from jaximu import simulate as simulate
from jaximu import so3 as so3
from jaximu import world as world
from jaximu.errorstate import discrete_process_noise as discrete_process_noise
from jaximu.errorstate import ekf_update as ekf_update
from jaximu.errorstate import propagate_covariance as propagate_covariance
from jaximu.errorstate import propagate_covariance_final as propagate_covariance_final
from jaximu.errorstate import step_jacobians as step_jacobians
from jaximu.integrators import ATTITUDES as ATTITUDES
from jaximu.integrators import SCHEMES as SCHEMES
from jaximu.noise import ImuNoise as ImuNoise
from jaximu.preintegration import Preintegrated as Preintegrated
from jaximu.preintegration import bias_jacobians_autodiff as bias_jacobians_autodiff
from jaximu.preintegration import compose as compose
from jaximu.preintegration import correct as correct
from jaximu.preintegration import needs_reintegration as needs_reintegration
from jaximu.preintegration import predict as predict
from jaximu.preintegration import preintegrate as preintegrate
from jaximu.preintegration import residual as residual
from jaximu.preintegration import whitened_residual as whitened_residual
from jaximu.propagate import propagate as propagate
from jaximu.propagate import propagate_final as propagate_final
from jaximu.sensor import SensorPose as SensorPose
from jaximu.state import ImuBias as ImuBias
from jaximu.state import NavState as NavState
from jaximu.state import boxminus as boxminus
from jaximu.state import boxplus as boxplus
from jaximu.world import earth_rate as earth_rate

__version__ = "0.1.0"
