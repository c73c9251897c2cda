"""IMU noise model: the four continuous-time densities of Kalibr, and their discretisation.

Units, the most asked question about every IMU library:

=============================  ===================  =====================================
field                          unit                 discrete equivalent over a sample dt
=============================  ===================  =====================================
gyroscope_noise_density        rad/s/√Hz            white-noise std  σ_g / √dt   [rad/s]
accelerometer_noise_density    m/s²/√Hz             white-noise std  σ_a / √dt   [m/s²]
gyroscope_random_walk          rad/s²/√Hz           bias step std    σ_bg · √dt  [rad/s]
accelerometer_random_walk      m/s³/√Hz             bias step std    σ_ba · √dt  [m/s²]
=============================  ===================  =====================================

The noise vector of one step is ``n = [n_g, n_a, n_wg, n_wa]`` (12), held constant over
the step ``[t_k, t_k + dt)``: ``w = w_m - b_g - n_g``, ``f = a_m - b_a - n_a``,
``b_g ← b_g + n_wg dt``, ``b_a ← b_a + n_wa dt``, with covariance
``Q_c = diag(σ_g², σ_a², σ_bg², σ_ba²) / dt`` (OpenVINS, Trawny eqs. 129-130). With the
noise Jacobian ``G`` of one step the discrete process noise is ``Q_d = G Q_c Gᵀ``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val

__all__ = ["ImuNoise"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities (Kalibr names and units).

    Each field is a scalar (isotropic), a ``(3,)`` per-axis value, or carries leading
    batch axes ``(..., 3)``. Fields are differentiable parameters.

    Attributes:
        gyroscope_noise_density: σ_g [rad/s/√Hz] (angle random walk).
        accelerometer_noise_density: σ_a [m/s²/√Hz] (velocity random walk).
        gyroscope_random_walk: σ_bg [rad/s²/√Hz] (gyro bias random walk).
        accelerometer_random_walk: σ_ba [m/s³/√Hz] (accel bias random walk).
    """

    gyroscope_noise_density: jax.Array | float
    accelerometer_noise_density: jax.Array | float
    gyroscope_random_walk: jax.Array | float = 0.0
    accelerometer_random_walk: jax.Array | float = 0.0

    @classmethod
    def euroc(cls) -> ImuNoise:
        """ADIS16448 of the EuRoC MAV dataset (its ``imu0/sensor.yaml``)."""
        return cls(1.6968e-04, 2.0000e-3, 1.9393e-05, 3.0000e-3)

    @classmethod
    def tum_vi(cls) -> ImuNoise:
        """BMI160 of the TUM-VI dataset (OpenVINS ``tum_vi`` config)."""
        return cls(0.00016, 0.0028, 2.2e-05, 0.00086)

    def _per_axis(self, dtype):
        """The four densities as ``dtype`` arrays ``(..., 3)``, checked as the propagation
        entries check them (numbers, not text or complex; finite and ``≥ 0`` when concrete)."""
        checked = check_noise(self, dtype)  # refuses complex and bool too (to_dtype)
        out = []
        for name in _FIELDS:
            f = getattr(checked, name)
            out.append(jnp.broadcast_to(f[..., None], f.shape + (3,)) if f.ndim == 0 else f)
        return out

    def sample_std(self, dt, dtype=None):
        """Per-sample standard deviations for a sample held over ``dt`` [s] (``> 0``, finite;
        checked on eager calls; a ``bool`` is refused).

        Computed in ``dtype`` (float32 or float64) if given, else in ``dt``'s floating dtype
        (an integer ``dt`` in the default float dtype, half precision in float32), never in
        an integer dtype. The densities are checked as :func:`jaximu.propagate_covariance`
        checks them (finite, ``≥ 0``).

        Returns:
            ``(gyro_white, accel_white, gyro_bias_step, accel_bias_step)``, each ``(..., 3)``:
            ``σ/√dt`` for the white noises and ``σ_rw·√dt`` for the bias steps.
        """
        dt = _dt_array(dt, dtype)
        sg, sa, sbg, sba = self._per_axis(dt.dtype)
        root = jnp.sqrt(dt)[..., None]
        return sg / root, sa / root, sbg * root, sba * root

    def discrete_covariance(self, dt, dtype=None):
        """``Q_c``: the ``(..., 12, 12)`` covariance of the step noise ``[n_g, n_a, n_wg, n_wa]``.

        Diagonal ``[σ_g², σ_a², σ_bg², σ_ba²] / dt`` (each over 3 axes); ``dt > 0``, finite;
        dtypes as :meth:`sample_std`.
        """
        var = self.discrete_variances(dt, dtype)
        return var[..., None] * jnp.eye(12, dtype=var.dtype)

    def variances(self, dtype=None):
        """``[σ_g², σ_a², σ_bg², σ_ba²]`` per axis, ``(..., 12)`` (densities squared), in
        ``dtype`` (float32 or float64; default: JAX's default float dtype)."""
        dtype = jnp.result_type(float) if dtype is None else val.compute_dtype("dtype", dtype)
        parts = [s * s for s in self._per_axis(dtype)]
        shape = jnp.broadcast_shapes(*(x.shape for x in parts))
        return jnp.concatenate([jnp.broadcast_to(x, shape) for x in parts], axis=-1)

    def discrete_variances(self, dt, dtype=None):
        """Diagonal of :meth:`discrete_covariance`: :meth:`variances` ``/ dt``, ``(..., 12)``.

        ``dt > 0`` and finite (a ``ValueError`` on eager calls: ``dt = 0`` would give inf,
        then NaN in ``G Q Gᵀ``); dtypes as :meth:`sample_std`."""
        dt = _dt_array(dt, dtype)
        return self.variances(dt.dtype) / dt[..., None]


_FIELDS = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)


def _dt_array(dt, dtype):
    """``dt`` as an array of the computation dtype: ``dtype`` (float32 or float64) if given,
    else ``dt``'s float dtype (at least float32), else JAX's default float dtype; positive
    and finite before and after the cast, when concrete."""
    kind = val.kind_of(dt)
    if kind == "b":
        raise ValueError("dt must be a time step in seconds, got a bool (True would be 1 s)")
    if dtype is not None:
        dtype = val.compute_dtype("dtype", dtype)
    elif kind == "f":
        dtype = val.float_dtype(dt)  # its own float dtype; half precision → float32
    else:  # integer steps: the default float dtype (text and ragged lists: refused below)
        dtype = jnp.result_type(float)
    arr = val.to_dtype("dt", dt, dtype)  # names dt if it is complex, text, None or ragged
    _check_dt(dt)
    try:
        _check_dt(arr)
    except ValueError:  # positive in the input, 0 in the computation dtype (1e-300 in float32)
        raise ValueError(
            f"dt must be positive and finite in the computation dtype "
            f"{jnp.dtype(dtype).name}; dt = {np.asarray(dt).min()} is 0 in it; "
            "pass float64 (with jax_enable_x64) or a larger dt"
        ) from None
    return arr


def _check_dt(dt):
    """``dt > 0`` and finite, when concrete (inside a caller's ``jit`` it is not checked)."""
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(dt)):
        return
    arr = np.asarray(dt)
    bad = ~(np.isfinite(arr) & (arr > 0))
    if bad.any():
        where = (
            ("[" + ", ".join(str(int(i)) for i in np.argwhere(bad)[0]) + "]") if arr.ndim else ""
        )
        value = arr[tuple(np.argwhere(bad)[0])] if arr.ndim else arr
        raise ValueError(
            f"dt must be positive and finite; dt{where} = {value} (the noise variances are σ²/dt)"
        )


def check_noise(noise, dtype, name: str = "noise"):
    """Types, shapes, finiteness and signs of the four densities; ``name``: the argument as
    the user wrote it (``settings.noise`` for a field of a settings record)."""
    if not isinstance(noise, ImuNoise):
        raise ValueError(f"{name} must be a jaximu.ImuNoise, got {type(noise).__name__}")
    fields = {}
    for density in (
        "gyroscope_noise_density",
        "accelerometer_noise_density",
        "gyroscope_random_walk",
        "accelerometer_random_walk",
    ):
        field = f"{name}.{density}"
        x = val.to_dtype(field, getattr(noise, density), dtype)
        if x.ndim > 0 and x.shape[-1] != 3:
            raise ValueError(
                f"{field} must be a scalar or have shape (..., 3), got {tuple(x.shape)}"
            )
        val.check_finite(field, x)
        if val.is_concrete(x) and np.any(np.asarray(x) < 0):
            raise ValueError(
                f"{field} must be non-negative, got {np.asarray(x)}: a density is σ, "
                "its sign would be lost in σ²; pass its magnitude"
            )
        fields[density] = x
    return ImuNoise(**fields)
