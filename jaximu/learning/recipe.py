"""The training recipe: :class:`TrainConfig`, the settings of
:func:`jaximu.learning.train`, and the optimizer they set (AdamW on a cosine schedule with
warm restarts). Its own module so that the settings, their checks and the step's compile key
(``_step_settings``) have one home apart from the loop that uses them."""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import optax

from jaximu.errors import Fix, InputError
from jaximu.geometry._checks import check_bool, check_int, check_positive
from jaximu.learning._selection import CRITERIA
from jaximu.learning.losses import check_horizons

__all__ = ["TrainConfig"]

_INTEGERS = {
    "steps": 1,
    "restart": 1,
    "offset": 1,
    "skip": 0,
    "validate_every": 1,
    "velocity_horizon": 1,
}
_NON_NEGATIVE = (
    "weight_decay",
    "gyro_noise",
    "accel_noise",
    "gyro_bias_noise",
    "accel_bias_noise",
    "nll_weight",
    "velocity_weight",
)

_FLAGS = (
    "calibrate_uncertainty",
    "recording_offsets",
    "whole_recordings",
    "bias_noise_shown",
    "bias_markov",
    "align_reference",
)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Settings of :func:`train` (JSON-serialisable).

    Attributes:
        steps: AdamW steps (one step sees every training part once: Brossard's epoch).
        learning_rate, min_learning_rate: cosine annealing with warm restarts between them
            (Brossard: 0.01 and 0.001 with BatchNorm; this network has no normalisation
            layer and trains stably at 0.003), periods ``restart`` then twice as long each time.
        restart: the first period [steps].
        weight_decay: AdamW's, on the convolution weights.
        train_seconds: the first seconds of each sequence are for training, the rest for
            validation (Brossard: 80).
        horizons: increment lengths of the loss [samples], each twice the one before
            (Brossard's 16, 32). Longer ones (32 … 2048, up to 10 s) gave a lower mean AOE
            on the validation parts (later seconds of the training recordings, whose bias
            they share) but a higher one on recordings left out of training: 4.93° against
            4.31° averaged over the five EuRoC training recordings each left out in turn,
            and above the constant bias on one (``benchmarks/learning_leave_one_out.py``).
        offset: random start offsets ``0 … offset-1`` [samples].
        skip: windows of the first horizon left out at each piece's start.
        gyro_noise, accel_noise: white noise added to the raw samples [rad/s], [m/s²]
            (Brossard's code: 8e-5, 1e-3).
        gyro_bias_noise, accel_bias_noise: standard deviation of a constant added per
            piece [rad/s], [m/s²] (Brossard's: uniform in ±1e-3, standard deviation 5.8e-4).
            The gyro's is the spread of the training sequences' biases about their mean
            (2–2.5e-3 rad/s on y and z): the network's input then varies by a bias as a new
            recording's does. The gyro's constant is added to the bias it is shown too (the
            tracker follows a constant bias), so the correction is not asked to remove it.
        bias_noise_shown: ``False``: the gyro's constant is not added to the bias shown,
            and the correction is asked to remove it (Brossard's, whose network is shown no
            bias: for a network without the tracker, which must read the bias itself).
            The network alone, MH_03 and V2_01 each left out: 0.81 × the constant bias at
            step 100 against 0.70 with the constant shown.
        nll_weight: weight of the negative log-likelihood (trains the noise outputs).
        validate_every: steps between validations.
        ema: decay of the exponential average of the weights that is validated and kept
            (``0``: the weights of the step).
        velocity_horizon, velocity_delta, velocity_weight: the accelerometer head's loss
            (``ModelConfig.accel_head``): Huber (``velocity_delta`` [m/s]) of the
            velocity-increment errors over windows of ``velocity_horizon`` samples
            (:func:`jaximu.learning.losses.velocity_residuals`), weighted.
        calibrate_uncertainty: after training, fit the ground truth's attitude noise
            ``σ_ref`` to the kept network by the likelihood of the training windows, then set
            the residual gyro bias ``σ_b`` on the validation parts
            (:mod:`jaximu.learning.uncertainty`); the validation parts' windowed NEES
            (1 s and 5 s, :func:`jaximu.learning.uncertainty.window_nees`) is recorded.
        bias_markov: with ``calibrate_uncertainty``, then fit a Gauss–Markov gyro bias
            (``ModelConfig.bias_markov_sigma``, ``bias_markov_time``) by the likelihood of
            the validation parts' windows of 1 s and 5 s
            (:func:`jaximu.learning.uncertainty.set_bias_markov`).
        selection: how the kept step is chosen: ``"validation"``, the lowest mean AOE on
            the validation parts (the later seconds of the training recordings, which share
            their bias), or ``"leave_one_out"``: each recording left out in turn and
            integrated whole by a model trained on the others, the step with the lowest
            mean over these folds kept of the model trained on all (the number of recordings
            plus one trainings; no recording chooses a model trained on it), or
            ``"leave_one_out_worst"``: the same folds, the step kept only if below the
            untrained network on every recording left out (the lowest worst ratio;
            :func:`jaximu.learning._selection.choose_step`).
        whole_recordings: train on pieces of ``train_seconds`` at random starts anywhere in
            each whole recording (a new start each step) instead of the first
            ``train_seconds``: no seconds are kept for validation, so only with
            a leave-one-out ``selection``, whose judges are the recordings left out (the
            later seconds still give the record's validation figures and the uncertainty's
            calibration, on seconds the network has seen). MH_03 and V2_01 each left out:
            1.08 × the tracker alone at step 100 against the first 80 s's 0.98
            (``benchmarks/learning_network_share.py``).
        recording_offsets: fit, beside the network, one constant gyro offset per training
            recording (summing to zero; dropped after training): what is left of each
            recording's own bias then has a place other than the network, which would
            otherwise learn to tell the recordings apart and carry their biases to
            recordings it never saw.
        align_reference: train on each training part's ground truth read at its own time
            offset from the integrated raw gyro (the mocap's clock and the integration's
            half-interval lag), fitted from the raw gyro
            (:func:`jaximu.learning.alignment.reference_offset`); the validation parts and
            the recordings left out keep the ground truth as recorded, as the evaluation
            does. TUM-VI's mocap agrees best read 3.3-3.4 ms earlier on rooms 1, 3 and 5:
            over the loss's windows that is 3-6 mrad of residual the network was trained to
            predict, and each room left out rose to 4-6° mean AOE within 50 steps; realigned,
            rooms 1 and 3 stayed within 2.5° over 100 steps
            (``benchmarks/results/learning-tumvi-recipe-amd-epyc-2cpu.json``).
    """

    steps: int = 300
    learning_rate: float = 0.003
    min_learning_rate: float = 0.0003
    restart: int = 300
    weight_decay: float = 0.1
    train_seconds: float = 80.0
    horizons: tuple = (16, 32)
    offset: int = 32
    skip: int = 4
    gyro_noise: float = 8e-5
    accel_noise: float = 1e-3
    gyro_bias_noise: float = 1.5e-3
    accel_bias_noise: float = 5.8e-4
    nll_weight: float = 1.0
    validate_every: int = 25
    calibrate_uncertainty: bool = True
    velocity_horizon: int = 200
    velocity_delta: float = 0.05
    velocity_weight: float = 1e3
    ema: float = 0.98
    recording_offsets: bool = True
    selection: str = "validation"
    bias_markov: bool = False
    whole_recordings: bool = False
    bias_noise_shown: bool = True
    align_reference: bool = False

    def __post_init__(self):
        name = "TrainConfig"
        h = check_horizons(f"{name}.horizons", self.horizons)
        object.__setattr__(self, "horizons", h)  # JSON gives a list
        for field, minimum in _INTEGERS.items():
            object.__setattr__(
                self, field, check_int(f"{name}.{field}", getattr(self, field), minimum)
            )
        for field in ("learning_rate", "min_learning_rate", "train_seconds", "velocity_delta"):
            check_positive(f"{name}.{field}", getattr(self, field))
        if self.min_learning_rate > self.learning_rate:
            raise InputError(
                f"{name}.min_learning_rate = {self.min_learning_rate!r} exceeds "
                f"learning_rate = {self.learning_rate!r}: the cosine annealing runs from "
                "learning_rate down to min_learning_rate",
                [Fix("min_learning_rate", float(f"{self.learning_rate / 10:.3g}"))],
                lead="pass at most learning_rate, e.g.",
            )
        for field in _NON_NEGATIVE:
            check_positive(f"{name}.{field}", getattr(self, field), allow_zero=True)
        if check_positive(f"{name}.ema", self.ema, allow_zero=True) >= 1.0:
            raise ValueError(f"{name}.ema must be in [0, 1) (0: no average), got {self.ema!r}")
        for field in _FLAGS:
            check_bool(f"{name}.{field}", getattr(self, field))
        if self.selection not in ("validation", *CRITERIA):
            raise ValueError(
                f"{name}.selection must be 'validation' or one of {CRITERIA}, got "
                f"{self.selection!r}"
            )

    def to_json(self) -> dict:
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()
        }


def _periods(cfg: TrainConfig) -> list[int]:
    """The cosine schedule's periods: ``restart`` steps, then each twice the one before,
    until they cover ``steps``."""
    periods: list[int] = []
    p = cfg.restart
    while sum(periods) < cfg.steps:
        periods.append(p)
        p *= 2
    return periods


def _schedule(cfg: TrainConfig):
    kw = dict(warmup_steps=0, end_value=cfg.min_learning_rate)
    return optax.sgdr_schedule(
        [
            dict(init_value=cfg.learning_rate, peak_value=cfg.learning_rate, decay_steps=p, **kw)
            for p in _periods(cfg)
        ]
    )


# Settings the step never reads (the noise levels enter it as arrays; the rest is the data's
# preparation, the validation and what follows the steps): set to their defaults in the
# step's static key (_step_settings), so trainings that differ only in them share one program.
_NOT_IN_STEP = (
    "train_seconds offset gyro_noise accel_noise gyro_bias_noise accel_bias_noise validate_every"
    " calibrate_uncertainty selection bias_markov whole_recordings align_reference"
).split()


def _step_settings(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` as the step sees it: the settings it never reads at their defaults, and
    ``steps`` at the end of the last warm restart it reaches (the schedule is the same for
    every ``steps`` within one period: 1 to 300 by default)."""
    defaults: dict[str, Any] = {name: getattr(TrainConfig, name) for name in _NOT_IN_STEP}
    return dataclasses.replace(cfg, steps=sum(_periods(cfg)), **defaults)


def _decay_mask(model):
    return jax.tree_util.tree_map(lambda x: eqx.is_array(x) and x.ndim == 3, model)


def _optimizer(cfg: TrainConfig, model):
    return optax.adamw(_schedule(cfg), weight_decay=cfg.weight_decay, mask=_decay_mask(model))
