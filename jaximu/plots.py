"""Plots for Monte Carlo studies and Allan deviations (needs matplotlib: ``jaximu[examples]``).

Every function draws into the axes it is given (or a new figure) and returns the figure.
"""

from __future__ import annotations

import numpy as np

__all__ = ["plot_monte_carlo", "plot_nees", "plot_allan"]

_BLOCKS = (("attitude error [deg]", 0, np.rad2deg(1.0)), ("position error [m]", 3, 1.0),
           ("velocity error [m/s]", 6, 1.0))


def _plt():
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("plots need matplotlib: pip install \"jaximu[examples]\"") from e
    return plt


def plot_monte_carlo(result, title: str | None = None, max_runs: int = 50):
    """3σ envelopes of the linearised covariance over the Monte Carlo error cloud.

    A 3×3 grid (attitude, position, velocity × x, y, z): the errors of up to ``max_runs``
    runs (grey), ±3σ predicted by the covariance (red) and ±3σ of the sample (blue, dashed).
    """
    plt = _plt()
    fig, axes = plt.subplots(3, 3, figsize=(13, 9), sharex=True)
    t = result.times
    for row, (label, i0, scale) in enumerate(_BLOCKS):
        for c, axis in enumerate("xyz"):
            ax = axes[row, c]
            i = i0 + c
            runs = result.sample_errors[:max_runs, :, i] * scale
            ax.plot(t, runs.T, color="0.6", lw=0.5, alpha=0.6)
            s_pred = 3 * np.sqrt(result.predicted_cov[:, i, i]) * scale
            s_emp = 3 * np.sqrt(result.error_cov[:, i, i]) * scale
            ax.plot(t, s_pred, "r-", lw=1.5, label="±3σ predicted")
            ax.plot(t, -s_pred, "r-", lw=1.5)
            ax.plot(t, s_emp, "b--", lw=1.2, label="±3σ Monte Carlo")
            ax.plot(t, -s_emp, "b--", lw=1.2)
            ax.set_title(f"{label.split(' [')[0]} {axis}", fontsize=9)
            if c == 0:
                ax.set_ylabel(label)
            if row == 2:
                ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=8, loc="upper left")
    fig.suptitle(title or f"Monte Carlo: {result.n_runs} runs, linearised 3σ vs sample 3σ")
    fig.tight_layout()
    return fig


def plot_nees(result, ax=None, title: str | None = None):
    """The average NEES over time with its χ² interval (expected value 15)."""
    plt = _plt()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(8, 4))
    lo, hi = result.nees_bounds
    ax.plot(result.times, result.nees_mean, "k.-", label="average NEES")
    ax.axhline(15, color="g", lw=1, label="expected (15)")
    ax.axhspan(lo, hi, color="g", alpha=0.15,
               label=f"{100 * result.confidence:.0f}% interval, N = {result.n_runs}")
    ax.set(xlabel="t [s]", ylabel="NEES", title=title or "Normalised estimation error squared")
    ax.legend(fontsize=8)
    return fig or ax.figure


def plot_allan(taus, adev, fit=None, labels=("x", "y", "z"), ax=None, unit="rad/s",
               title: str | None = None):
    """Allan deviation (log-log) per axis, with the fitted white-noise (slope -1/2) and
    random-walk (slope +1/2) lines when ``fit`` (:class:`jaximu.allan.NoiseFit`) is given."""
    plt = _plt()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(7, 5))
    adev = np.asarray(adev)
    adev = adev[:, None] if adev.ndim == 1 else adev
    for j in range(adev.shape[1]):
        line, = ax.loglog(taus, adev[:, j], ".-", label=f"σ({labels[j]})")
        if fit is not None:
            w = np.atleast_1d(fit.white)[j]
            k = np.atleast_1d(fit.random_walk)[j]
            ax.loglog(taus, w / np.sqrt(taus), ":", color=line.get_color(), lw=1)
            ax.loglog(taus, k * np.sqrt(taus / 3), "--", color=line.get_color(), lw=1)
    ax.set(xlabel="τ [s]", ylabel=f"Allan deviation [{unit}]",
           title=title or "Allan deviation (dotted: white noise, dashed: random walk)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig or ax.figure
