"""The Monte Carlo study's host side (:func:`jaximu.montecarlo.monte_carlo`): the streaming
float64 sums over the runs, their exchange between processes, and the progress line."""

from __future__ import annotations

import sys
import time

import jax
import numpy as np

# --------------------------------------------------------------------------- progress


class _Progress:
    """tqdm when installed, else a line on stderr every second: runs done, runs/s, ETA."""

    def __init__(self, total, enabled):
        self.total, self.done, self.bar = total, 0, None
        self.enabled = enabled
        self.t0 = self.last = time.perf_counter()
        if enabled:
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(total=total, unit="run", desc="Monte Carlo")
            except ImportError:
                pass

    def update(self, n):
        self.done += n
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n)
            return
        now = time.perf_counter()
        if now - self.last >= 1.0 or self.done == self.total:
            self.last = now
            rate = self.done / max(now - self.t0, 1e-9)
            eta = (self.total - self.done) / max(rate, 1e-9)
            print(
                f"\rMonte Carlo: {self.done}/{self.total} runs, {rate:,.0f} runs/s, "
                f"ETA {eta:.0f} s",
                end="",
                file=sys.stderr,
                flush=True,
            )

    def close(self):
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            print(file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- accumulation


class _Acc:
    """Streaming sums over runs, float64 on the host: count, mean and centred second moment
    of the errors per recorded time (Chan, Golub, LeVeque's pairwise update), the sum of the
    NEES, and NEES histograms."""

    def __init__(self, K, hist_index, edges):
        self.n = 0
        self.mean = np.zeros((K, 15))
        self.M2 = np.zeros((K, 15, 15))
        self.nees_sum = np.zeros(K)
        self.hist_index = hist_index
        self.edges = edges
        self.hist = np.zeros((len(hist_index), len(edges) - 1))
        self.nis_sum = np.zeros(K)  # filter study
        self.P_sum = np.zeros((K, 15, 15))

    def add_moments(self, n_b, mean_b, M2_b):
        n_a = self.n
        n = n_a + n_b
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (n_b / n)
        self.M2 = self.M2 + M2_b + np.einsum("ki,kj->kij", delta, delta) * (n_a * n_b / n)
        self.n = n

    def add_chunk(self, n_b, mean_b, M2_b, nees, P_sum=None, nis=None):
        """``nees``: ``(K, n_b)`` per-run NEES of the chunk's valid runs (filter study: also
        the sum of the runs' covariances and ``(K, n_b)`` NIS)."""
        self.add_moments(n_b, np.asarray(mean_b, np.float64), np.asarray(M2_b, np.float64))
        if P_sum is not None:
            self.P_sum += np.asarray(P_sum, np.float64)
            self.nis_sum += nis.sum(1)
        self.nees_sum += nees.sum(1)
        last = len(self.edges) - 2
        for h, k in enumerate(self.hist_index):
            b = np.clip(np.searchsorted(self.edges, nees[k], side="right") - 1, 0, last)
            self.hist[h] += np.bincount(b, minlength=last + 1)

    def add(self, other):
        if other.n:
            self.add_moments(other.n, other.mean, other.M2)
        self.nees_sum += other.nees_sum
        self.hist += other.hist
        self.nis_sum += other.nis_sum
        self.P_sum += other.P_sum

    _PARTS = ("mean", "M2", "nees_sum", "hist", "nis_sum", "P_sum")

    def pack(self):
        return np.concatenate([[self.n]] + [getattr(self, k).ravel() for k in self._PARTS])

    def unpack(self, flat):
        K = len(self.nees_sum)
        other = _Acc(K, self.hist_index, self.edges)
        i = 1
        other.n = int(flat[0])
        for name in self._PARTS:
            shape = getattr(self, name).shape
            size = int(np.prod(shape))
            setattr(other, name, flat[i : i + size].reshape(shape))
            i += size
        return other


def _allgather_f64(x):
    """Every process's float64 vector ``x`` (same length), exactly: sent as uint32 words (the
    transport does not need ``jax_enable_x64``). Returns ``(processes, len)``."""
    from jax.experimental import multihost_utils

    words = np.ascontiguousarray(x, np.float64).view(np.uint32)
    out = np.asarray(multihost_utils.process_allgather(words))
    return out.reshape(jax.process_count(), -1).view(np.float64)
