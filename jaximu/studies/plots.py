"""Plots of trajectories against ground truth, Monte Carlo studies and Allan deviations
(needs matplotlib: ``jaximu[examples]``).

Every function draws into the axes it is given (or a new figure) and returns the figure.
"""

from __future__ import annotations

import numpy as np

from jaximu.io import trajectory_errors

__all__ = ["plot_trajectory", "plot_monte_carlo", "plot_nees", "plot_allan"]

_BLOCKS = (
    ("attitude error [deg]", 0, np.rad2deg(1.0)),
    ("position error [m]", 3, 1.0),
    ("velocity error [m/s]", 6, 1.0),
)


def _plt():
    try:
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError('plots need matplotlib: pip install "jaximu[examples]"') from e
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
    ax.axhspan(
        lo,
        hi,
        color="g",
        alpha=0.15,
        label=f"{100 * result.confidence:.0f}% interval, N = {result.n_runs}",
    )
    ax.set(xlabel="t [s]", ylabel="NEES", title=title or "Normalised estimation error squared")
    ax.legend(fontsize=8)
    return fig or ax.figure


def plot_allan(
    taus, adev, fit=None, labels=("x", "y", "z"), ax=None, unit="rad/s", title: str | None = None
):
    """Allan deviation (log-log) per axis, with the fitted white-noise (slope -1/2) and
    random-walk (slope +1/2) lines when ``fit`` (:class:`jaximu.allan.NoiseFit`) is given."""
    plt = _plt()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(7, 5))
    adev = np.asarray(adev)
    adev = adev[:, None] if adev.ndim == 1 else adev
    for j in range(adev.shape[1]):
        (line,) = ax.loglog(taus, adev[:, j], ".-", label=f"σ({labels[j]})")
        if fit is not None:
            w = np.atleast_1d(fit.white)[j]
            k = np.atleast_1d(fit.random_walk)[j]
            ax.loglog(taus, w / np.sqrt(taus), ":", color=line.get_color(), lw=1)
            ax.loglog(taus, k * np.sqrt(taus / 3), "--", color=line.get_color(), lw=1)
    ax.set(
        xlabel="τ [s]",
        ylabel=f"Allan deviation [{unit}]",
        title=title or "Allan deviation (dotted: white noise, dashed: random walk)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return fig or ax.figure


def plot_trajectory(
    t, states, ground_truth=None, cov=None, *, label: str = "jaximu", title: str | None = None
):
    """Trajectory against ground truth, with the errors and their 3σ envelopes.

    Top row: top view (x-y, world frame) and height against time. With ground truth, two
    more rows: the position error per axis and the orientation error per axis (body frame,
    ``Log(Rᵀ R̂)``, degrees), each with ±3σ of the propagated covariance when ``cov`` is given.

    Args:
        t: ``(T,)`` times [s]; states: :class:`jaximu.NavState` with ``(T, ·)`` fields;
        ground_truth: :class:`jaximu.io.GroundTruth` on the same clock, or ``None``;
        cov: ``(T, 15, 15)`` covariances of ``[dθ, dp, dv, db_g, db_a]``, or ``None``.
    """
    plt = _plt()
    t = np.asarray(t, np.float64)
    p = np.asarray(states.p, np.float64)
    rows = 1 if ground_truth is None else 3
    fig = plt.figure(figsize=(13, 3.6 * rows + 0.6))
    grid = fig.add_gridspec(rows, 3)
    top = fig.add_subplot(grid[0, :2])
    height = fig.add_subplot(grid[0, 2])
    t0 = t[0]
    if ground_truth is not None:
        gt = ground_truth
        span = (gt.t >= t[0] - 1e-5) & (gt.t <= t[-1] + 1e-5)
        top.plot(gt.p[span, 0], gt.p[span, 1], "k-", lw=2, label="ground truth")
        height.plot(gt.t[span] - t0, gt.p[span, 2], "k-", lw=2, label="ground truth")
    top.plot(p[:, 0], p[:, 1], "C0-", lw=1.2, label=label)
    top.plot(p[:1, 0], p[:1, 1], "go", label="start")
    top.set(title="Top view (world frame)", xlabel="x [m]", ylabel="y [m]", aspect="equal")
    top.legend(fontsize=8)
    height.plot(t - t0, p[:, 2], "C0-", lw=1.2, label=label)
    height.set(title="Height", xlabel="t [s]", ylabel="z [m]")
    height.legend(fontsize=8)
    if ground_truth is not None:
        err = trajectory_errors(t, states, ground_truth, cov)
        te = err.t - t0
        for row, (name, values, i0, scale, unit) in enumerate(
            (
                ("position error", err.position, 3, 1.0, "m"),
                ("orientation error", err.rotation, 0, np.rad2deg(1.0), "deg"),
            ),
            start=1,
        ):
            for c, axis in enumerate("xyz"):
                ax = fig.add_subplot(grid[row, c])
                ax.plot(te, values[:, c] * scale, "C0.-", ms=2, lw=1, label=f"{label} − truth")
                if err.sigma is not None:
                    s3 = 3 * err.sigma[:, i0 + c] * scale
                    ax.fill_between(te, -s3, s3, color="C1", alpha=0.2, label="±3σ (propagated)")
                ax.axhline(0, color="k", lw=0.5)
                ax.set(title=f"{name} {axis}", xlabel="t [s]", ylabel=f"[{unit}]")
                if c == 0:
                    ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(title or f"{label}: trajectory" + (" against ground truth" if rows > 1 else ""))
    fig.tight_layout()
    return fig
