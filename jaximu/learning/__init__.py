"""IMU integration inside learned models (``pip install "jaximu[learning]"``: equinox).

A causal dilated convolution corrects the raw gyro (and optionally the accelerometer) and
predicts a per-sample gyro noise density (:class:`Denoiser`, Brossard et al. 2020's network
in equinox), on top of the gyro bias tracked from gravity over the whole recording so far
(:func:`track_gyro_bias`: an EKF on jaximu's propagation, no ground truth). It is trained through jaximu's own batched preintegration on orientation
increments, with the likelihood of the increment errors under the covariance that jaximu
propagates from the learned density (:func:`train`), and evaluated on whole sequences
integrated open loop from the first true attitude (:func:`evaluate_sequence`), and over
windows of seconds each started from the true attitude (:func:`window_nees`, the
uncertainty's consistency where the whole run's NEES is dominated by its bias).
"""

from jaximu.learning.checkpoint import load, pretrained, save
from jaximu.learning.data import Sequence, load_sequence, split
from jaximu.learning.evaluation import (
    Metrics,
    SequenceReport,
    attitude_covariance,
    evaluate_sequence,
    integrate_attitude,
    orientation_errors,
)
from jaximu.learning.model import CausalConv, Corrected, Denoiser, ModelConfig
from jaximu.learning.recipe import TrainConfig
from jaximu.learning.tracking import Tracked, TrackerSettings, track_gyro_bias
from jaximu.learning.training import TrainResult, train
from jaximu.learning.uncertainty import fit_bias_markov, window_nees

__all__ = [
    "Denoiser",
    "ModelConfig",
    "Corrected",
    "CausalConv",
    "track_gyro_bias",
    "TrackerSettings",
    "Tracked",
    "Sequence",
    "load_sequence",
    "split",
    "TrainConfig",
    "TrainResult",
    "train",
    "evaluate_sequence",
    "integrate_attitude",
    "orientation_errors",
    "attitude_covariance",
    "window_nees",
    "fit_bias_markov",
    "Metrics",
    "SequenceReport",
    "save",
    "load",
    "pretrained",
]
