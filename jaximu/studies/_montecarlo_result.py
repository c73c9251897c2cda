"""What a Monte Carlo study returns (:class:`MonteCarloResult`), its files (save and load) and
the NEES bounds' χ² interval.
"""

from __future__ import annotations

import json
import math
import pathlib
from typing import Any, NamedTuple

import numpy as np

from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val


class MonteCarloResult(NamedTuple):
    """Statistics of a Monte Carlo study (numpy arrays, float64; K recorded times).

    Attributes:
        times: ``(K,)`` recorded times [s].
        mean_error: ``(K, 15)`` mean of ``e_k`` over the runs.
        error_cov: ``(K, 15, 15)`` empirical covariance of ``e_k`` (N - 1 normalisation).
        predicted_cov: ``(K, 15, 15)`` open loop: the linearised covariance; filter study:
            the average over the runs of each run's own covariance after the update.
        nees: ``(N, K)`` NEES of every run at every recorded time with ``keep_nees=True``,
            else ``None`` (memory ``N·K``); NaN where the NEES is undefined (below).
        nees_mean: ``(K,)`` average NEES over the runs. NaN at a recorded time where the
            covariance is singular to the precision of the computation dtype
            (:func:`jaximu.geometry._tolerances.definiteness`; the filter study's judged on the runs'
            average): ``eᵀ P⁻¹ e`` is undefined there, e.g. in the first steps from an
            exactly known start (``P0 = 0``), where one step's position and velocity errors
            are the same accelerometer noise (:attr:`nees_defined`).
        nees_bounds: ``(2,)`` the two-sided interval of the average NEES at ``confidence``.
        sample_errors: ``(n_keep, K, 15)`` the errors of the first runs (for plots).
        discretization_error: ``(K, 15)`` noise-free propagation ⊟ true trajectory.
        n_runs: N.
        confidence: the interval's confidence.
        nees_hist: ``(H, nbins)`` counts of the per-run NEES at the recorded times
            ``nees_hist_index`` (values past the last edge in the last bin; NaN where the
            NEES is undefined).
        nees_hist_edges: ``(nbins + 1,)`` the bins' edges.
        nees_hist_index: ``(H,)`` indices into ``times`` of the histograms.
        nis_mean: filter study: ``(K,)`` average NIS at the updates (else ``None``).
        nis_bounds: filter study: ``(2,)`` its interval (dof ``m N``), else ``None``.
        settings: the options that produced the result (a dict; JSON-serialisable).
    """

    times: np.ndarray
    mean_error: np.ndarray
    error_cov: np.ndarray
    predicted_cov: np.ndarray
    nees: np.ndarray | None
    nees_mean: np.ndarray
    nees_bounds: np.ndarray
    sample_errors: np.ndarray
    discretization_error: np.ndarray
    n_runs: int
    confidence: float
    nees_hist: np.ndarray | None = None
    nees_hist_edges: np.ndarray | None = None
    nees_hist_index: np.ndarray | None = None
    nis_mean: np.ndarray | None = None
    nis_bounds: np.ndarray | None = None
    settings: dict | None = None

    @property
    def consistent(self) -> np.ndarray:
        """``(K,)``: whether the average NEES lies inside its interval at each time (False
        where it is undefined: :attr:`nees_defined`)."""
        return (self.nees_mean >= self.nees_bounds[0]) & (self.nees_mean <= self.nees_bounds[1])

    @property
    def nees_defined(self) -> np.ndarray:
        """``(K,)``: whether the NEES is defined at each recorded time (the covariance there
        is positive definite to the computation dtype's precision; see ``nees_mean``)."""
        return np.isfinite(self.nees_mean)

    def save(self, path) -> None:
        """Write the result (and its settings, as JSON) to ``path``, an ``.npz`` file in an
        existing folder (:func:`load_result` reads it back). A path without the ``.npz``
        suffix is refused (numpy would silently write ``path + ".npz"``)."""
        p = _result_path(path)
        if p.suffix.lower() != ".npz":
            raise InputError(
                f"path {str(p)!r} must end in .npz (numpy would write {str(p) + '.npz'!r} instead)",
                [Fix("path", str(p) + ".npz")],
            )
        if p.is_dir():
            raise ValueError(f"path {str(p)!r} is a folder; name an .npz file in it")
        if not p.parent.is_dir():
            raise ValueError(f"path {str(p)!r}: the folder {str(p.parent)!r} does not exist")
        arrays: dict[str, Any] = {
            k: np.asarray(v)
            for k, v in self._asdict().items()
            if v is not None and k not in ("settings", "n_runs", "confidence")
        }
        meta = dict(
            settings=self.settings or {},
            n_runs=self.n_runs,
            confidence=self.confidence,
            format=_FORMAT,
        )
        arrays["__meta__"] = np.asarray(json.dumps(meta))
        np.savez(p, **arrays)


_FORMAT = "jaximu.montecarlo/1"


_REQUIRED = (
    "times",
    "mean_error",
    "error_cov",
    "predicted_cov",
    "nees_mean",
    "nees_bounds",
    "sample_errors",
    "discretization_error",
)


def _result_path(path) -> pathlib.Path:
    try:
        return pathlib.Path(path)
    except TypeError:
        raise ValueError(
            f"path must be a file name (str or os.PathLike), got {type(path).__name__}"
        ) from None


def load_result(path) -> MonteCarloResult:
    """Read a result written by :meth:`MonteCarloResult.save`. ``path``: that ``.npz`` file;
    a missing file, a folder, another kind of file, another ``.npz`` or a damaged result
    raise an error naming the file (``FileNotFoundError`` or ``ValueError``)."""
    import zipfile

    p = _result_path(path)
    if p.is_dir():
        raise ValueError(f"path {str(p)!r} is a folder, not a result file (.npz)")
    if not p.is_file():
        raise FileNotFoundError(
            f"path {str(p)!r}: no such file (a result written by MonteCarloResult.save)"
        )
    not_ours = f"{str(p)!r} is not a jaximu Monte Carlo result (written by MonteCarloResult.save)"
    if not zipfile.is_zipfile(p):
        raise ValueError(f"{not_ours}: not an .npz archive")
    with np.load(p, allow_pickle=False) as f:
        if "__meta__" not in f.files:
            raise ValueError(
                f"{not_ours}: it holds the arrays {sorted(f.files)[:8]} and no format tag"
            )
        try:
            meta = json.loads(str(f["__meta__"]))
            fmt = meta.get("format")
        except (ValueError, AttributeError):
            raise ValueError(f"{not_ours}: its __meta__ is not the JSON settings") from None
        if fmt != _FORMAT:
            raise ValueError(
                f"{not_ours}: its format tag is {fmt!r}, this version reads {_FORMAT!r}"
            )
        fields = {k: f[k] for k in f.files if k != "__meta__"}
    missing = [k for k in _REQUIRED if k not in fields]
    absent = [k for k in ("n_runs", "confidence") if k not in meta]
    if missing or absent:
        raise ValueError(
            f"{str(p)!r} is a damaged Monte Carlo result: {', '.join(missing + absent)} missing"
        )
    stats: dict[str, Any] = {
        k: fields.get(k)
        for k in MonteCarloResult._fields
        if k not in ("settings", "n_runs", "confidence")
    }
    return MonteCarloResult(
        **stats,
        n_runs=int(meta["n_runs"]),
        confidence=float(meta["confidence"]),
        settings=meta.get("settings"),
    )


def chi2_interval(dof, confidence: float = 0.95):
    """Two-sided interval of a ``χ²(dof)`` variable by the Wilson-Hilferty approximation
    (no scipy needed). Relative error at 99%: 1.2% at dof 15, 2e-4 at 150, 5e-6 at 1500,
    5e-8 at 30000 (the average NEES of N runs has dof 15 N). ``dof > 0``; ``confidence``
    in ``(0, 1)`` (0.95, not 95). Returns ``(lo, hi)``."""
    from jax.scipy.special import ndtri

    k = val.check_positive("dof", dof)
    confidence = val.check_fraction("confidence", confidence)
    z = float(ndtri(0.5 + confidence / 2))
    c = 2.0 / (9.0 * k)
    return (k * (1 - c - z * math.sqrt(c)) ** 3, k * (1 - c + z * math.sqrt(c)) ** 3)
