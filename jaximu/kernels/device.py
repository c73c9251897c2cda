"""The kind of device the kernels are compiled for, and the lanes a block fills there."""

from __future__ import annotations

import contextlib

import jax

CPU, ACCELERATOR = "cpu", "accelerator"


def backend() -> str:
    """The kind of device the kernels are compiled for: :data:`CPU`, or :data:`ACCELERATOR`
    (a GPU or TPU: JAX's default backend when it is not the CPU). The structure-of-arrays
    layout is tuned for XLA:CPU; on an accelerator a step is one launch over every lane, so
    a batch is one block and the table's ``backends`` column keeps only the rows measured to
    pay there (docs/DESIGN.md, "Dispatch" and "On a GPU"). Under ``jax.default_device(d)``
    (or ``jax_default_device`` set) it is the kind of ``d``: the kernels run where the
    computation does (the setting is part of JAX's jit key, so each kind is traced apart)."""
    d = getattr(jax.config, "jax_default_device", None)
    platform = jax.default_backend() if d is None else getattr(d, "platform", d)
    return CPU if platform == "cpu" else ACCELERATOR


def host_device():
    """A context in which JAX computes on the host's CPU (and the dispatch table picks the
    CPU's kernels, :func:`backend`) when the default backend is an accelerator; nothing
    otherwise. For the sequential work of one trajectory that a study prepares before its
    batch (docs/DESIGN.md section 6)."""
    if jax.default_backend() == "cpu":
        return contextlib.nullcontext()
    try:
        cpu = jax.local_devices(backend="cpu")[0]
    except RuntimeError:  # JAX_PLATFORMS without the CPU: compute where the rest does
        return contextlib.nullcontext()
    return jax.default_device(cpu)


ACCELERATOR_LANES = 1 << 16
"""Lanes of one batch block on an accelerator, and the lanes the time chunks of long
sequences aim to fill there: a launch over 65536 lanes fills a GPU (an H100 holds about
270 000 threads), and every block or chunk fewer is a sequential step fewer."""
