"""Trajectories out and back: TUM pose files and states with covariances (CSV or NPZ)."""

from __future__ import annotations

import pathlib

import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.state import NavState  # noqa: PLC0415
from jaximu.io._common import DataError
from jaximu.io._text import _parse, _parse_tum, _read_table

_INT64_MAX = np.iinfo(np.int64).max
# the covariances are judged with float32's rounding whatever dtype they arrive in (one
# computed in float32 and stored as float64 passes): _tolerances.check_variances
_COV_DTYPE = np.float32


def _check_t0_ns(t0_ns) -> int:
    """``t0_ns`` as an ``int``: an integer number of nanoseconds (never parsed, rounded or
    truncated for the user)."""
    if isinstance(t0_ns, np.ndarray) and t0_ns.ndim == 0 and t0_ns.dtype.kind in "iu":
        t0_ns = t0_ns[()]  # a 0-d integer array (np.load(...)["t0_ns"])
    if isinstance(t0_ns, (bool, np.bool_)) or not isinstance(t0_ns, (int, np.integer)):
        hint = (
            "; pass an int such as data.t0_ns"
            if not isinstance(t0_ns, (float, np.floating))
            else ": a float cannot hold epoch nanoseconds exactly; pass data.t0_ns"
        )
        raise ValueError(
            f"t0_ns must be an integer number of nanoseconds, got "
            f"{type(t0_ns).__name__} {t0_ns!r}{hint}"
        )
    t0 = int(t0_ns)
    if abs(t0) > _INT64_MAX:
        raise ValueError(f"t0_ns = {t0} is beyond int64 nanoseconds")
    return t0


def _check_times(t, T=None) -> np.ndarray:
    """``t`` as a finite ``(T,)`` float64 array of seconds."""
    arr = val.as_numbers("t", t)
    if arr.ndim != 1 or (T is not None and len(arr) != T):
        want = "(T,)" if T is None else f"({T},) (one time per state)"
        raise ValueError(f"t must have shape {want}, got {arr.shape}")
    val.check_finite("t", arr)
    return arr


def _stamps(t, t0_ns):
    """Absolute int64 ns stamps from seconds since ``t0_ns`` (exact for ns-grid times);
    ``t`` must be finite (:func:`_check_times`) and the stamps inside int64."""
    t0 = _check_t0_ns(t0_ns)
    ns = np.round(np.asarray(t, np.float64) * 1e9)
    total = ns + float(t0)
    bad = np.abs(total) > 9.2e18  # int64 holds ±9.22e18 (t0_ns + ns could wrap)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"t[{i}] = {float(t[i]):.6g} s is beyond int64 nanoseconds (with t0_ns = {t0}): "
            "t is seconds since t0_ns; pass data.t, not stamps_ns"
        )
    return t0 + ns.astype(np.int64)


def _check_cov(cov, T, name="cov") -> np.ndarray:
    """``cov`` ``(T, 15, 15)``, finite, with no negative variance (judged relative to the
    largest entry of each matrix); returns it as float64."""
    cov = val.as_numbers(name, cov)
    if cov.shape != (T, 15, 15):
        raise ValueError(
            f"{name} must have shape ({T}, 15, 15) (one 15×15 covariance per "
            f"state), got {cov.shape}"
        )
    val.check_finite(name, cov)
    _tolerances.check_variances(
        name,
        cov,
        _COV_DTYPE,
        fix="pass the covariance the propagation returned, not a difference of covariances",
    )
    return cov


def _sigma(var):
    """Standard deviations of variances checked by :func:`_check_cov`: those within
    rounding below zero (``-60 ε`` of float32 times their matrix's largest entry) are read
    as 0."""
    return np.sqrt(np.maximum(var, 0.0))


def _seconds_text(ns):
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    return f"{sign}{abs(ns) // 10**9}.{abs(ns) % 10**9:09d}"


def _pose_arrays(states):
    q = val.as_numbers("states.q", states.q)
    p = val.as_numbers("states.p", states.p)
    if q.ndim != 2 or p.ndim != 2 or q.shape[1] != 4 or p.shape[1] != 3 or len(q) != len(p):
        raise ValueError(
            f"states must hold one trajectory: q (T, 4), p (T, 3); got {q.shape}, {p.shape}"
        )
    val.check_finite("states.q", q)
    val.check_finite("states.p", p)
    return q, p


def write_tum(path, t, states, *, t0_ns: int = 0) -> None:
    """Write poses in the TUM trajectory format, one ``t tx ty tz qx qy qz qw`` per line.

    This is what ``evo`` (``evo_ape tum gt.txt est.txt``) and the TUM RGB-D tools read.

    Args:
        path: output file.
        t: ``(T,)`` times [s] since ``t0_ns``; written as absolute seconds with all nine
            decimals, from integer nanoseconds (no float rounding of the epoch).
        states: a :class:`jaximu.NavState` (or anything with ``q`` ``(T, 4)`` Hamilton
            ``[w, x, y, z]`` of ``R_WB`` and ``p`` ``(T, 3)``); the file has ``[x, y, z, w]``.
        t0_ns: the epoch of ``t = 0`` [ns] (:attr:`ImuData.t0_ns`).
    """
    q, p = _pose_arrays(states)
    t = _check_times(t, len(q))
    stamps = _stamps(t, t0_ns)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (jaximu: W z-up, q of R_WB)\n")
        for s, pk, qk in zip(stamps, p, q):
            f.write(
                f"{_seconds_text(s)} {pk[0]:.9f} {pk[1]:.9f} {pk[2]:.9f} "
                f"{qk[1]:.9f} {qk[2]:.9f} {qk[3]:.9f} {qk[0]:.9f}\n"
            )


def read_tum(path):
    """Read a TUM trajectory file.

    Returns:
        ``(stamps_ns, p, q)``: ``(T,)`` int64 ns (exact from the decimal text), ``(T, 3)``,
        ``(T, 4)`` Hamilton ``[w, x, y, z]`` (converted from the file's ``[x, y, z, w]``).
    """
    _, rows, lines = _read_table(path, None)
    stamps, values = _parse_tum(rows, lines, path)
    return stamps, values[:, 0:3], values[:, 3:7]


_STATE_FIELDS = (
    ("q", ("w", "x", "y", "z")),
    ("p", "xyz"),
    ("v", "xyz"),
    ("b_g", "xyz"),
    ("b_a", "xyz"),
)
_ERROR_NAMES = [f"{b}_{c}" for b in ("theta", "p", "v", "b_g", "b_a") for c in "xyz"]


def write_states(path, t, states, cov=None, *, t0_ns: int = 0, full_covariance: bool = True):
    """Write states (and covariances) to CSV or NPZ, by the file's suffix.

    CSV: a header line, then per state ``stamp_ns, t, q_w … q_z, p_x …, v_x …, b_g_x …,
    b_a_x …``, then the standard deviations ``sigma_theta_x … sigma_b_a_z`` (error state
    ``[dθ, dp, dv, db_g, db_a]``, rotation error on the right) and, with
    ``full_covariance``, the upper triangle of ``P`` as ``P_i_j``. NPZ: arrays
    ``stamps_ns, t, q, p, v, b_g, b_a`` and ``cov`` ``(T, 15, 15)``.

    Args:
        t: ``(T,)`` [s] since ``t0_ns``.
        states: a :class:`jaximu.NavState` with ``(T, ·)`` fields.
        cov: ``(T, 15, 15)`` or ``None``.
    """
    path = pathlib.Path(path)
    full_covariance = val.check_bool("full_covariance", full_covariance)
    arrays = {
        name: val.as_numbers(f"states.{name}", getattr(states, name)) for name, _ in _STATE_FIELDS
    }
    T = len(arrays["q"]) if arrays["q"].ndim else 0
    if np.ndim(t) != 1 or len(t) != T or any(a.ndim != 2 or len(a) != T for a in arrays.values()):
        raise ValueError(
            f"t (T,) and states with (T, ·) fields expected; got t {np.shape(t)}, "
            + ", ".join(f"{k} {a.shape}" for k, a in arrays.items())
        )
    for name, a in arrays.items():
        val.check_finite(f"states.{name}", a)
    t = _check_times(t, T)
    if cov is not None:
        cov = _check_cov(cov, T)
    stamps = _stamps(t, t0_ns)
    if path.suffix == ".npz":
        fields = dict(stamps_ns=stamps, t=t, t0_ns=np.int64(t0_ns), **arrays)
        if cov is not None:
            fields["cov"] = cov
        np.savez(path, **fields)
        return
    if path.suffix != ".csv":
        raise ValueError(f"write_states writes .csv or .npz, not {path.suffix!r}")
    cols = ["stamp_ns", "t"] + [f"{n}_{c}" for n, comps in _STATE_FIELDS for c in comps]
    block = [np.asarray(t, np.float64)[:, None]] + [arrays[n] for n, _ in _STATE_FIELDS]
    if cov is not None:
        cols += [f"sigma_{n}" for n in _ERROR_NAMES]
        block.append(_sigma(np.diagonal(cov, axis1=1, axis2=2)))
        if full_covariance:
            iu = np.triu_indices(15)
            cols += [f"P_{i}_{j}" for i, j in zip(*iu)]
            block.append(cov[:, iu[0], iu[1]])
    values = np.concatenate(block, axis=1)
    with open(path, "w") as f:
        f.write(",".join(cols) + "\n")
        for s, row in zip(stamps, values):
            f.write(f"{s}," + ",".join(repr(float(x)) for x in row) + "\n")


def read_states(path):
    """Read what :func:`write_states` wrote.

    Returns:
        ``(stamps_ns, states, cov)``: int64 ``(T,)``, a :class:`jaximu.NavState` of numpy
        float64 arrays, and ``(T, 15, 15)`` (``None`` if not written; from a CSV without the
        full covariance, diagonal from the standard deviations).
    """
    path = pathlib.Path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            states = NavState(*(z[n] for n, _ in _STATE_FIELDS))
            return z["stamps_ns"], states, (z["cov"] if "cov" in z.files else None)
    header, rows, lines = _read_table(path, ",")
    if header is None or header[0] != "stamp_ns":
        raise DataError(f"{path}: not a jaximu states CSV (no 'stamp_ns' header)")
    stamps, values = _parse(rows, lines, 0, range(1, len(header)), "ns", path)
    col = {name: i - 1 for i, name in enumerate(header)}
    take = lambda names: values[:, [col[n] for n in names]]  # noqa: E731
    states = NavState(*(take([f"{n}_{c}" for c in comps]) for n, comps in _STATE_FIELDS))
    cov = None
    if "P_0_0" in col:
        cov = np.zeros((len(stamps), 15, 15))
        for i, j in zip(*np.triu_indices(15)):
            cov[:, i, j] = cov[:, j, i] = values[:, col[f"P_{i}_{j}"]]
    elif "sigma_theta_x" in col:
        sig = take([f"sigma_{n}" for n in _ERROR_NAMES])
        cov = sig[:, :, None] ** 2 * np.eye(15)
    return stamps, states, cov
