"""The denoising network: a causal dilated 1-D convolution over raw IMU samples (Brossard,
Bonnabel & Barrau, RA-L 2020), with heads for the gyro correction, a per-sample noise
density, and optionally the accelerometer.

Layout is channels-last, ``(batch, time, channel)``: for this network on this project's
2-core CPU (8 base channels, 6 × 8,000 samples, forward + backward + Adam) a JAX step took
117-157 ms channels-last against 183-234 ms with PyTorch's channels-first
``(batch, channel, time)``.

Corrected samples, per sample ``k`` (``ω_m``, ``a_m`` raw, ``y`` the network's outputs)::

    ω̂_k = (I + C) ω_m,k - b̂_g,k + s_g ⊙ y_g,k        C: a learned 3×3 matrix (scale, misalignment)
    ω̂_k = ω_m,k - b̂_g,k + C (ω_m,k - b̂_g,k) + s_g ⊙ y_g,k     (``matrix_after_bias``)
    â_k = a_m,k - b̄_a + s_a ⊙ y_a,k                  (with the accelerometer head)
    σ_g,k = σ̄_g · exp(3 tanh(y_σ,k / 3))              gyro noise density [rad/s/√Hz]

``b̄_g``, ``b̄_a`` are the constant biases stored with the model (the training sequences' mean
ground-truth bias: the "constant bias" baseline). ``b̂_g,k`` is the gyro bias tracked from
gravity over all samples before ``k`` (:mod:`jaximu.learning.tracking`), starting at ``b̄_g``
(``bias_tracking=False``: ``b̄_g`` throughout). The network sees 2.5 s of samples; a new
recording's bias is a property of the whole recording, which only a long-memory estimate
reads. An untrained network (last layer zero, ``C = 0``) is the tracked (or constant) bias
alone, and training learns what it misses.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaximu.errors import Fix, InputError
from jaximu.geometry._checks import (
    check_array,
    check_bool,
    check_finite,
    check_int,
    check_key,
    check_output,
    check_positive,
    check_vector,
    float_dtype,
    is_concrete,
    to_dtype,
)
from jaximu.geometry.noise import ImuNoise
from jaximu.learning.tracking import Tracked, TrackerSettings, check_settings, track_gyro_bias

__all__ = ["ModelConfig", "Corrected", "CausalConv", "Denoiser"]


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Everything that defines a :class:`Denoiser` besides its weights (JSON-serialisable).

    Attributes:
        rate_hz: the IMU rate the model was trained at [Hz]; other rates are refused.
        channels: output channels of the dilated convolutions (Brossard: 16, 32, 64, 128).
        kernel: kernel size of each dilated convolution (Brossard: 7).
        dilations: dilation of each convolution (Brossard: 1, 4, 16, 64).
        dropout: dropout rate after each convolution while training.
        input_mean, input_std: per-channel normalisation of ``[ω_m, a_m]`` (6 each).
        gyro_bias, accel_bias: the constant biases ``b̄_g`` [rad/s], ``b̄_a`` [m/s²].
        gyro_scale: ``s_g`` [rad/s] per axis (Brossard's 1, 2, 5 °/s).
        accel_scale: ``s_a`` [m/s²] per axis.
        gyro_density: ``σ̄_g`` [rad/s/√Hz], the density at a zero noise output.
        gyro_random_walk: ``σ_bg`` [rad/s²/√Hz] of the residual bias (the datasheet's).
        bias_sigma, reference_sigma: initial values of the learned residual gyro bias
            ``σ_b`` [rad/s] and the ground truth's attitude noise ``σ_ref`` [rad].
        accel_head: whether the accelerometer is corrected too.
        accel_network: with ``accel_head``, whether the accelerometer's correction comes
            from convolution layers of its own (the gyro's layers, kernel and dilations,
            initialised from another key) instead of a second head on the gyro's layers:
            the velocity loss then trains no weight of the gyro correction, and the
            training keeps each part from its own best step (the gyro's by the attitude,
            the accelerometer's by the dead-reckoning windows; :func:`train`).
        bias_tracking: whether the gyro bias is tracked from gravity
            (:mod:`jaximu.learning.tracking`) instead of held at ``gyro_bias``.
        gyro_bias_sigma, accel_bias_sigma: the tracker's prior standard deviations of the
            biases about ``gyro_bias``, ``accel_bias`` [rad/s], [m/s²] (:func:`train` sets them
            from the training sequences' spread: :func:`jaximu.learning.training.bias_spreads`).
        accel_density, accel_random_walk: the accelerometer's noise densities [m/s²/√Hz],
            [m/s³/√Hz] (the datasheet's), for the tracker.
        velocity_sigma: [m/s] the tracker's bound on the true velocity (``v = 0 ± σ``): a
            vehicle that stays near its start (a drone in a room, a handheld device); raise
            it for one that travels, or set ``bias_tracking=False``.
        update_samples: samples between the tracker's updates.
        standstill: whether the tracker takes the bias about the vertical from windows of
            1 s at rest (:mod:`jaximu.learning.tracking`; a model saved without this
            setting loads with it off, as it was trained).
        bias_markov_sigma, bias_markov_time: a slowly varying part of the residual gyro
            bias, a first-order Gauss–Markov process per axis (``ḃ = -b/τ + w``) of
            stationary standard deviation ``σ_m`` [rad/s] and correlation time ``τ`` [s]
            (the orientation covariance's term beside the constant ``σ_b`` and the random
            walk; :func:`jaximu.learning.uncertainty.fit_bias_markov` sets them). ``σ_m = 0``
            (a model saved without them): none.
        matrix_after_bias: whether ``C`` scales the rate with its bias removed,
            ``C (ω_m - b̂_g)`` (a scale or misalignment error acts on the true rate),
            instead of ``C ω_m``, which with EuRoC's biases of up to 0.08 rad/s carries
            ``C b`` (~1e-4 rad/s for ``|C|`` ~ 1e-3), a bias of its own. Measured on
            EuRoC recordings left out of training, it did not change what the network
            adds (``benchmarks/learning_network_share.py``), so it is off by default (and
            for a model saved without it).
    """

    rate_hz: float = 200.0
    channels: tuple = (16, 32, 64, 128)
    kernel: int = 7
    dilations: tuple = (1, 4, 16, 64)
    dropout: float = 0.1
    input_mean: tuple = (0.0,) * 6
    input_std: tuple = (1.0,) * 6
    gyro_bias: tuple = (0.0, 0.0, 0.0)
    accel_bias: tuple = (0.0, 0.0, 0.0)
    gyro_scale: tuple = tuple(float(x) for x in np.radians([1.0, 2.0, 5.0]))
    accel_scale: tuple = (0.1, 0.1, 0.1)
    gyro_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    bias_sigma: float = 1e-3
    reference_sigma: float = 1e-3
    accel_head: bool = False
    bias_tracking: bool = True
    gyro_bias_sigma: tuple = (2.5e-3, 2.5e-3, 2.5e-3)
    accel_bias_sigma: tuple = (0.02, 0.02, 0.02)
    accel_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    velocity_sigma: float = 1.0
    update_samples: int = 20
    standstill: bool = True
    bias_markov_sigma: float = 0.0
    bias_markov_time: float = 60.0
    matrix_after_bias: bool = False
    accel_network: bool = False

    def __post_init__(self):
        for field in (
            "channels",
            "dilations",
            "input_mean",
            "input_std",
            "gyro_bias",
            "accel_bias",
            "gyro_scale",
            "accel_scale",
            "gyro_bias_sigma",
            "accel_bias_sigma",
        ):  # JSON gives lists
            value = getattr(self, field)
            if isinstance(value, (str, bytes)) or not np.iterable(value):
                raise ValueError(
                    f"ModelConfig.{field} must be a sequence of numbers, got {value!r}"
                )
            object.__setattr__(self, field, tuple(value))
        name = "ModelConfig"
        check_positive(f"{name}.rate_hz", self.rate_hz)
        for field in ("channels", "dilations"):  # whole numbers, kept as ints
            widths = tuple(
                check_int(f"{name}.{field}[{i}]", c, 1) for i, c in enumerate(getattr(self, field))
            )
            object.__setattr__(self, field, widths)
        if check_positive(f"{name}.dropout", self.dropout, allow_zero=True) >= 1.0:
            raise ValueError(f"{name}.dropout must be in [0, 1), got {self.dropout!r}")
        for field, n, low in (
            ("input_mean", 6, None),
            ("input_std", 6, "positive"),
            ("gyro_bias", 3, None),
            ("accel_bias", 3, None),
            ("gyro_scale", 3, "non-negative"),
            ("accel_scale", 3, "non-negative"),
        ):  # n finite numbers, of a sign where ``low`` says
            v = check_array(f"{name}.{field}", getattr(self, field), (n,))
            if (low == "positive" and not np.all(v > 0)) or (
                low == "non-negative" and np.any(v < 0)
            ):
                raise ValueError(f"{name}.{field} must be {n} {low} numbers, got {v.tolist()}")
        for field in (
            "gyro_density",
            "gyro_random_walk",
            "accel_density",
            "accel_random_walk",
            "bias_sigma",
            "reference_sigma",
        ):  # densities; the last two are stored as logarithms
            check_positive(f"{name}.{field}", getattr(self, field))
        check_positive(
            f"{name}.bias_markov_sigma",
            self.bias_markov_sigma,
            allow_zero=True,
            hint=" [rad/s]: pass 0 for no Gauss–Markov bias",
        )
        check_positive(
            f"{name}.bias_markov_time",
            self.bias_markov_time,
            hint=" [s]: pass the bias's correlation time, e.g. 60.0",
        )
        if len(self.channels) != len(self.dilations):
            raise ValueError(
                f"ModelConfig: channels {self.channels} and dilations "
                f"{self.dilations} must have the same length (one per layer)"
            )
        # the tracker's settings, checked where the tracker checks them (before tracker()
        # divides by update_samples)
        check_settings(self._tracker(standstill_samples=0), "ModelConfig")
        for field in ("bias_tracking", "standstill", "accel_head", "matrix_after_bias"):
            check_bool(f"{name}.{field}", getattr(self, field))
        if check_bool(f"{name}.accel_network", self.accel_network) and not self.accel_head:
            raise InputError(
                f"{name}.accel_network = True gives the accelerometer's correction layers of "
                "its own, but accel_head is False (no accelerometer correction)",
                [Fix("accel_head", True), Fix("accel_network", False)],
            )
        kernel = check_int(f"{name}.kernel", self.kernel, 1, "a positive odd number")
        if kernel % 2 == 0:
            raise InputError(
                f"{name}.kernel must be a positive odd number (a causal convolution's "
                f"taps), got {self.kernel!r}",
                [Fix("kernel", kernel + 1)],
            )
        object.__setattr__(self, "kernel", kernel)

    def tracker(self) -> TrackerSettings:
        """The gyro-bias tracker's settings (:mod:`jaximu.learning.tracking`)."""
        per_second = max(1, round(self.rate_hz / self.update_samples))  # 1 s in whole blocks
        return self._tracker(per_second * self.update_samples if self.standstill else 0)

    def _tracker(self, standstill_samples: int) -> TrackerSettings:
        return TrackerSettings(
            self.gyro_bias,
            self.accel_bias,
            self.gyro_bias_sigma,
            self.accel_bias_sigma,
            ImuNoise(
                self.gyro_density,
                self.accel_density,
                self.gyro_random_walk,
                self.accel_random_walk,
            ),
            velocity_sigma=self.velocity_sigma,
            update_samples=self.update_samples,
            standstill_samples=standstill_samples,
        )

    @property
    def receptive_field(self) -> int:
        """Samples the output at ``k`` depends on (``k - receptive_field + 1 … k``)."""
        return 1 + (self.kernel - 1) * int(sum(self.dilations))

    @property
    def bias_markov(self) -> tuple[float, float] | None:
        """``(σ_m [rad/s], τ [s])`` of the Gauss–Markov bias, or None without one."""
        if self.bias_markov_sigma > 0:
            return (float(self.bias_markov_sigma), float(self.bias_markov_time))
        return None

    @property
    def corrections(self) -> int:
        """Correction outputs per sample of the gyro's layers: the gyro's 3, and the
        accelerometer's 3 when it has no layers of its own."""
        return 3 + (3 if self.accel_head and not self.accel_network else 0)

    def to_json(self) -> dict:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_json(cls, d: dict) -> ModelConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(
                f"unknown model settings {unknown}: the model was written by "
                "another version of jaximu"
            )
        # a model saved before the standstill updates was trained without them
        return cls(**{"standstill": False, "matrix_after_bias": False, **d})


class Corrected(NamedTuple):
    """The corrected samples and their noise, each ``(..., T, 3)``.

    Attributes:
        gyro: ω̂ [rad/s]; accel: â [m/s²] (the raw samples minus ``b̄_a`` without the head).
        gyro_density: σ_g per sample and axis [rad/s/√Hz].
        gyro_bias_sigma: the standard deviation of the subtracted gyro bias [rad/s] (the
            tracker's; zero for the constant bias or a bias given to the call).
    """

    gyro: jax.Array
    accel: jax.Array
    gyro_density: jax.Array
    gyro_bias_sigma: jax.Array


class CausalConv(eqx.Module):
    """A causal dilated 1-D convolution on ``(batch, time, channel)``: the output at ``k``
    sees inputs ``k - (kernel-1)·dilation … k``; the start is padded by repeating the first
    sample (Brossard's replication padding), so no step of the sequence is dropped."""

    weight: jax.Array  # (kernel, in, out)
    bias: jax.Array  # (out,)
    dilation: int = eqx.field(static=True)

    def __init__(self, c_in: int, c_out: int, kernel: int, dilation: int, key, zero=False):
        c_in, c_out = check_int("c_in", c_in, 1), check_int("c_out", c_out, 1)
        kernel, dilation = check_int("kernel", kernel, 1), check_int("dilation", dilation, 1)
        key = check_key("key", key)
        bound = 1.0 / np.sqrt(c_in * kernel)  # PyTorch's default for Conv1d
        kw, kb = jax.random.split(key)
        shape = (kernel, c_in, c_out)
        self.weight = (
            jnp.zeros(shape, jnp.float32)
            if zero
            else jax.random.uniform(kw, shape, jnp.float32, -bound, bound)
        )
        self.bias = (
            jnp.zeros((c_out,), jnp.float32)
            if zero
            else jax.random.uniform(kb, (c_out,), jnp.float32, -bound, bound)
        )
        self.dilation = int(dilation)

    def __call__(self, x):
        pad = (self.weight.shape[0] - 1) * self.dilation
        if pad:
            x = jnp.concatenate([jnp.repeat(x[:, :1], pad, axis=1), x], axis=1)
        y = jax.lax.conv_general_dilated(
            x,
            self.weight,
            (1,),
            "VALID",
            rhs_dilation=(self.dilation,),
            dimension_numbers=("NWC", "WIO", "NWC"),
        )
        return y + self.bias


FITTED = (
    "input_mean",
    "input_std",
    "gyro_bias",
    "accel_bias",
    "gyro_bias_sigma",
    "accel_bias_sigma",
)
"""The :class:`ModelConfig` fields a training sets from its data
(:func:`jaximu.learning.training.train`): the model holds them as arrays
(:class:`Fitted`), not in its static structure."""


class Fitted(eqx.Module):
    """The numbers of :data:`FITTED`, as float64 numpy arrays ``(6,)`` or ``(3,)`` (the
    settings' own values, exactly). They are leaves of the model, not part of its static
    structure, so a compiled program (a training step, a validation) serves models that
    differ only in them (each fold of a leave-one-out training); they are not trained."""

    input_mean: np.ndarray
    input_std: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    gyro_bias_sigma: np.ndarray
    accel_bias_sigma: np.ndarray

    def __init__(self, config: ModelConfig):
        for name in FITTED:
            setattr(self, name, np.asarray(getattr(config, name), np.float64))


class Denoiser(eqx.Module):
    """Gyro (and optionally accelerometer) denoiser with a per-sample gyro noise density.

    Call ``model(gyro, accel)`` with raw ``(..., T, 3)`` samples at ``config.rate_hz``;
    returns :class:`Corrected` in the samples' dtype (the network computes in its weights'
    dtype: float32 as trained; ``model.astype(jnp.float64)`` for float64 throughout).
    Pass ``key`` to apply dropout (training).
    """

    layers: tuple
    head: CausalConv  # corrections
    noise_head: CausalConv  # log-density, on the features without their gradient
    gyro_matrix: jax.Array  # C, (3, 3)
    accel_layers: tuple  # the accelerometer's own layers (ModelConfig.accel_network), or ()
    accel_out: CausalConv | None  # their correction (accel_network), or None
    log_bias_sigma: jax.Array  # log σ_b [rad/s]: the gyro bias the correction misses
    log_reference_sigma: jax.Array  # log σ_ref [rad]: the ground truth's attitude noise
    fitted: Fitted  # the settings the training data set (FITTED)
    structure: ModelConfig = eqx.field(static=True)  # the settings, FITTED at their defaults

    def __init__(self, config: ModelConfig, key):
        if not isinstance(config, ModelConfig):
            raise ValueError(
                f"config must be a jaximu.learning.ModelConfig, got {type(config).__name__}"
            )
        keys = jax.random.split(check_key("key", key), len(config.channels) + 1)
        widths = (6,) + tuple(config.channels)
        self.layers = tuple(
            CausalConv(widths[i], widths[i + 1], config.kernel, d, keys[i])
            for i, d in enumerate(config.dilations)
        )
        # the last layer starts at zero: the untrained model is the constant-bias baseline
        self.head = CausalConv(widths[-1], config.corrections, 1, 1, keys[-1], zero=True)
        self.noise_head = CausalConv(widths[-1], 3, 1, 1, keys[-1], zero=True)
        self.gyro_matrix = jnp.zeros((3, 3), jnp.float32)
        # the accelerometer's own layers from another key: the gyro's start as without them
        ka = jax.random.split(jax.random.fold_in(keys[-1], 1), len(config.channels) + 1)
        own = config.accel_network
        self.accel_layers = tuple(
            CausalConv(widths[i], widths[i + 1], config.kernel, d, ka[i])
            for i, d in enumerate(config.dilations)
            if own
        )
        self.accel_out = CausalConv(widths[-1], 3, 1, 1, ka[-1], zero=True) if own else None
        self.log_bias_sigma = jnp.asarray(np.log(config.bias_sigma), jnp.float32)
        self.log_reference_sigma = jnp.asarray(np.log(config.reference_sigma), jnp.float32)
        self.fitted = Fitted(config)
        self.structure = dataclasses.replace(
            config, **{name: getattr(ModelConfig, name) for name in FITTED}
        )

    @property
    def config(self) -> ModelConfig:
        """The model's :class:`ModelConfig`: its structure with the fitted numbers. Inside
        a traced function that takes the model as an argument, the fitted fields are the
        traced arrays (read with ``jnp``, never hashed)."""
        values = {name: getattr(self.fitted, name) for name in FITTED}
        concrete = is_concrete(list(values.values()))
        cfg = copy.copy(self.structure)  # (its fields were checked when the model was built)
        for name, v in values.items():
            object.__setattr__(cfg, name, tuple(float(x) for x in np.asarray(v)) if concrete else v)
        return cfg

    def astype(self, dtype) -> Denoiser:
        """The same model with its weights in ``dtype`` (e.g. float64 for gradient checks)."""
        return jax.tree_util.tree_map(
            lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, self
        )

    @property
    def bias_sigma(self):
        """σ_b [rad/s]: the residual gyro bias, a prior of the orientation covariance."""
        return jnp.exp(self.log_bias_sigma)

    @property
    def reference_sigma(self):
        """σ_ref [rad]: the ground truth's attitude noise (in every increment's two ends)."""
        return jnp.exp(self.log_reference_sigma)

    def features(self, gyro, accel, key=None):
        """``(corrections, log-density)``: the network's raw outputs ``(..., T, ·)`` in the
        weights' dtype (float32 as trained). The noise head reads the features without
        their gradient: the trunk is trained by the corrections' loss alone, the noise head
        by the likelihood."""
        cfg = self.config
        wdtype = self.head.weight.dtype  # float32 as trained; float64 after a cast
        x = jnp.concatenate([gyro, accel], -1).astype(wdtype)
        lead = x.shape[:-2]
        x = x.reshape((-1,) + x.shape[-2:])
        x = (x - jnp.asarray(cfg.input_mean, wdtype)) / jnp.asarray(cfg.input_std, wdtype)
        h = self._trunk(self.layers, x, key)
        y, z = self.head(h), self.noise_head(jax.lax.stop_gradient(h))
        if self.accel_out is not None:  # the accelerometer's own layers, dropout of its own
            k = None if key is None else jax.random.fold_in(key, 1)
            y = jnp.concatenate([y, self.accel_out(self._trunk(self.accel_layers, x, k))], -1)
        return y.reshape(lead + y.shape[-2:]), z.reshape(lead + z.shape[-2:])

    def _trunk(self, layers, x, key):
        """The dilated convolutions ``layers`` with GELU over normalised inputs ``x``
        ``(B, T, 6)``, dropout when ``key`` is given."""
        cfg = self.config
        keys = (None,) * len(layers) if key is None else jax.random.split(key, len(layers))
        for layer, k in zip(layers, keys):
            x = jax.nn.gelu(layer(x))
            if k is not None and cfg.dropout > 0:
                keep = jax.random.bernoulli(k, 1.0 - cfg.dropout, x.shape)
                x = jnp.where(keep, x / (1.0 - cfg.dropout), 0.0)
        return x

    def track(self, gyro, accel) -> Tracked:
        """The gyro bias ``b̂_g`` at every sample ``(..., T, 3)`` and its standard deviation,
        tracked from gravity (:func:`jaximu.learning.tracking.track_gyro_bias`), or the
        constant ``b̄_g`` (standard deviation 0) without ``bias_tracking``."""
        cfg = self.config
        gyro, accel = _samples(gyro, accel)
        dtype = gyro.dtype
        if cfg.bias_tracking:
            return track_gyro_bias(gyro, accel, 1.0 / cfg.rate_hz, cfg.tracker())
        b = jnp.broadcast_to(jnp.asarray(cfg.gyro_bias, dtype), jnp.shape(gyro))
        return Tracked(b, jnp.zeros_like(b))

    def __call__(self, gyro, accel, key=None, gyro_bias=None) -> Corrected:
        """Corrected samples; ``gyro``, ``accel``: ``(..., T, 3)`` finite; ``gyro_bias``:
        ``(..., T, 3)`` the tracked bias when already computed (:meth:`track`; training
        passes it, the tracker being fixed), or any finite shape that broadcasts to
        ``gyro``'s without changing it (``(3,)``: one bias). On eager calls the weights,
        the samples and the outputs are checked finite, each named in the error."""
        cfg = self.config
        check_weights("model", self)
        gyro, accel = _samples(gyro, accel)
        dtype = gyro.dtype
        if gyro_bias is not None:
            gyro_bias = to_dtype("gyro_bias", gyro_bias, dtype)
            try:
                fits = jnp.broadcast_shapes(gyro_bias.shape, gyro.shape) == gyro.shape
            except ValueError:
                fits = False
            if not fits or gyro_bias.ndim < 1 or gyro_bias.shape[-1] != 3:
                raise ValueError(
                    f"gyro_bias must have gyro's shape {tuple(gyro.shape)} (a bias per sample, "
                    f"as model.track(gyro, accel) gives) or (3,), got {tuple(gyro_bias.shape)}; "
                    "leave it out to track the bias"
                )
            check_finite("gyro_bias", gyro_bias, "pass finite biases [rad/s]")
        y, z = self.features(gyro, accel, key)
        y, z = y.astype(dtype), z.astype(dtype)
        C = self.gyro_matrix.astype(dtype)
        if gyro_bias is None:
            gyro_bias, bias_sigma = self.track(gyro, accel)
        else:
            bias_sigma = jnp.zeros(jnp.shape(gyro), dtype)
        scaled = gyro - gyro_bias if cfg.matrix_after_bias else gyro
        w = gyro + scaled @ C.T - gyro_bias + jnp.asarray(cfg.gyro_scale, dtype) * y[..., 0:3]
        a = accel - jnp.asarray(cfg.accel_bias, dtype)
        if cfg.accel_head:
            a = a + jnp.asarray(cfg.accel_scale, dtype) * y[..., 3:6]
        density = cfg.gyro_density * jnp.exp(3.0 * jnp.tanh(z / 3.0))
        out = Corrected(w, a, density, jnp.asarray(bias_sigma, dtype))
        return check_output("Denoiser", out, "gyro or accel too large")


def _samples(gyro, accel):
    """``gyro``, ``accel`` as arrays ``(..., T, 3)`` of one shape in their floating dtype
    (integers: float32, as the engine computes them); anything else raises naming them."""
    dtype = float_dtype(gyro, accel)
    g, a = to_dtype("gyro", gyro, dtype), to_dtype("accel", accel, dtype)
    check_vector("gyro", g)
    check_vector("accel", a)
    if g.shape != a.shape:
        raise ValueError(
            f"gyro and accel must have one shape (..., T, 3), got {tuple(g.shape)} and "
            f"{tuple(a.shape)}"
        )
    if g.shape[-2] < 1:
        raise ValueError(f"gyro and accel hold no samples (shape {tuple(g.shape)})")
    fix = "repair or drop those samples (the readers' drop_nonfinite=True)"
    check_finite("gyro", g, fix)
    check_finite("accel", a, fix)
    return g, a


def check_weights(name: str, model) -> None:
    """On a concrete model: every weight finite; else a ``ValueError`` naming ``name``, the
    first non-finite weight's place and how many there are (a training that diverged)."""
    leaves = jax.tree_util.tree_leaves_with_path(eqx.filter(model, eqx.is_inexact_array))
    if not is_concrete([x for _, x in leaves]):
        return
    for path, x in leaves:
        bad = ~np.isfinite(np.asarray(x))
        if bad.any():
            where = jax.tree_util.keystr(path) + (
                "[" + ", ".join(str(int(k)) for k in np.argwhere(bad)[0]) + "]" if bad.ndim else ""
            )
            n = int(sum(int((~np.isfinite(np.asarray(y))).sum()) for _, y in leaves))
            raise ValueError(
                f"{name}'s weights hold {n} non-finite values (NaN or inf), first in "
                f"{name}{where}: its training diverged; retrain it (a lower "
                "TrainConfig.learning_rate) or use another model"
            )


def check_model(name: str, model) -> Denoiser:
    """``model`` must be a :class:`Denoiser` (named ``name`` in the message) whose weights
    are finite (:func:`check_weights`)."""
    if not isinstance(model, Denoiser):
        raise ValueError(
            f"{name} must be a jaximu.learning.Denoiser (from train, load or "
            f"pretrained), got {type(model).__name__}"
        )
    check_weights(name, model)
    return model


def constant_bias(config: ModelConfig, gyro, accel):
    """The baseline the model starts from: raw samples minus the stored constant biases."""
    dtype = jnp.result_type(gyro, accel)
    return (
        gyro - jnp.asarray(config.gyro_bias, dtype),
        accel - jnp.asarray(config.accel_bias, dtype),
    )


def without_network(model: Denoiser) -> Denoiser:
    """``model`` with its network's correction zeroed (the corrections' head and the matrix
    ``C``): the tracked bias alone (or the constant bias without ``bias_tracking``), its
    learned noise density and uncertainty kept: what the network adds is the difference."""
    check_model("model", model)
    zero = jnp.zeros_like
    return eqx.tree_at(
        lambda m: (m.head.weight, m.head.bias, m.gyro_matrix),
        model,
        (zero(model.head.weight), zero(model.head.bias), zero(model.gyro_matrix)),
    )
