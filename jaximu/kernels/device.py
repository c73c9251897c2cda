"""The kind of device the kernels are compiled for, and the lanes a block fills there."""

from __future__ import annotations

import jax

CPU, ACCELERATOR = "cpu", "accelerator"


def backend() -> str:
    """The kind of device the kernels are compiled for: :data:`CPU`, or :data:`ACCELERATOR`
    (a GPU or TPU: JAX's default backend when it is not the CPU). The structure-of-arrays
    layout is tuned for XLA:CPU; on an accelerator a step is one launch over every lane, so
    a batch is one block and the table's ``backends`` column keeps only the rows measured to
    pay there (docs/DESIGN.md, "Dispatch" and "On a GPU")."""
    return CPU if jax.default_backend() == "cpu" else ACCELERATOR


ACCELERATOR_LANES = 1 << 16
"""Lanes of one batch block on an accelerator, and the lanes the time chunks of long
sequences aim to fill there: a launch over 65536 lanes fills a GPU (an H100 holds about
270 000 threads), and every block or chunk fewer is a sequential step fewer."""
