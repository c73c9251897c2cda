"""Which kernel runs: one table for every engine entry (docs/DESIGN.md, "Dispatch").

The engine has two families of kernels:

* ``generic``: readable ``lax.scan`` kernels on ``(..., 3)`` arrays, for every scheme,
  attitude form and Jacobian option. They are the reference the fast kernels are tested
  against (``fast=False`` forces them).
* structure-of-arrays kernels (:mod:`jaximu.kernels.soa`, :mod:`jaximu.kernels.fast`,
  :mod:`jaximu.kernels.fast_preint`): the same mathematics laid out for XLA:CPU's vectoriser.

A ``jax.vmap`` of an entry reaches this table with the whole batch (:mod:`jaximu.engine._batching`),
so the same row decides for leading axes and for ``vmap``. The table is read top to bottom;
the first row whose conditions hold names the kernel, and :func:`implementation` returns the
function that runs it (each engine module registers its own with :func:`implements`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp

from jaximu.kernels import soa as _soa
from jaximu.kernels.device import ACCELERATOR as ACCELERATOR
from jaximu.kernels.device import ACCELERATOR_LANES as ACCELERATOR_LANES
from jaximu.kernels.device import CPU as CPU
from jaximu.kernels.device import backend as backend
from jaximu.kernels.fast_preint import MIN_CHUNK

MIN_CHUNK_STEPS = 32
"""Shortest time chunk of a long sequence."""

MEAN_CHUNK_STEPS = 128
"""From this many steps an accelerator computes the mean in time chunks (each sequential
step there is a launch), up to :data:`MEAN_CHUNK_LANES` batch elements (docs/DESIGN.md,
"Dispatch"): 4 chunks of :data:`MIN_CHUNK_STEPS`, so that every state stored, whose chunks
run twice, still takes half the sequential launches. Measured on an NVIDIA H100
(``benchmarks/chunk_crossover.py``, run time): one float32 trajectory's final state ran
1.6× faster chunked at 64 steps and 3.0× at 128, every state stored 2.2× at 128; 64 is not
taken because every state stored was not measured there."""

MEAN_CHUNK_LANES = ACCELERATOR_LANES // 2
"""Up to this many batch elements the mean's time chunks run on an accelerator: at least 2
chunks a sequence (:func:`mean_chunks`). A mean step's work per lane is small against its
launch, so the launches saved pay for the chunks' extra lanes; more elements fill the lanes
themselves. Measured on an NVIDIA H100 at 200 float32 steps: chunks 3.6× faster at 1024 and
16384 sequences, 2.1× at 32768."""

COV_CHUNK_STEPS = {"cpu": 2048, "accelerator": 128}
"""From this many steps the covariance of a few sequences runs in time chunks
(``soa_cov_chunked``), by backend (docs/DESIGN.md, "Dispatch"). The CPU's: one trajectory's
final covariance ran as fast both ways at 1024 float64 steps (0.32 against 0.40 ms) and
twice as fast chunked from 2048 (float32 0.38 against 0.74 ms), run time alone (the chunks
compile in about 3.5 s against 1 s). The accelerator's: 4 chunks of
:data:`MIN_CHUNK_STEPS`; on an NVIDIA H100 (``benchmarks/chunk_crossover.py``, float64, run
time) one trajectory's final covariance ran 3.0× faster chunked at 128 steps, 5.6× at 256,
10× at 512, and every covariance stored 3.9× at 256 and 7.4× at 512 (at 128 not measured:
its chunks run twice, 64 launches and the composition against 128). The chunks compile
longer there (6–8.5 s against 2–2.3 s)."""

COV_CHUNK_LANES = {"cpu": 8, "accelerator": 2048}
"""Up to this many sequences the covariance runs in time chunks, by backend. The CPU: each
sequence's chunks fill a block of lanes (more sequences fill it themselves). An accelerator:
the chunks' lanes do the sequential scan's work and carry their transitions' bias columns
too, so their extra lanes cost more as the batch fills the device. On an NVIDIA H100, 256
float64 steps (``benchmarks/chunk_crossover.py``, final covariance, run time): chunks 4.0×
faster at 1024 sequences, as fast at 4096 (0.97×), slower at 16384 (0.64×); 2048 lies
inside the measured win."""


class Row(NamedTuple):
    entry: str  # "mean", "covariance", "preintegrate"
    schemes: tuple  # schemes the kernel implements
    attitudes: tuple | None  # attitude forms (None: not applicable)
    jacobians: tuple | None  # Jacobian options (None: not applicable)
    save_all: tuple  # (False,) final only, (False, True) both
    min_lanes: int  # below this many batch elements the generic kernel is as fast
    min_steps: int  # fewer steps than this: the row does not apply
    kernel: str
    dtypes: tuple = ("float32", "float64")
    rotating: tuple = (False,)  # omega_coriolis given (rotating world): (False,) = no
    lever: tuple | None = (False,)  # a sensor's lever arm in the Jacobians (None: no Jacobians)
    backends: tuple = (CPU, ACCELERATOR)  # where the row applies (backend())
    max_lanes: int | None = None  # more batch elements than this: the row does not apply


LANE_ATTITUDES = ("quaternion", "quaternion_first_order", "matrix", "euler_angles")
"""Every attitude form: each runs on the structure-of-arrays kernels as its own lanes
(:data:`jaximu.kernels.lane_forms.LANE_FORMS`), the mean and the autodiff covariance (the closed forms:
the exact exponentials only)."""

TABLE = (
    # mean of every scheme in every lane attitude form, a batch of 32 or more
    Row(
        "mean",
        ("euler", "midpoint", "rk4"),
        LANE_ATTITUDES,
        None,
        (False, True),
        32,
        1,
        "soa_mean",
        rotating=(False, True),
        lever=None,
        backends=(CPU,),
    ),
    # on an accelerator a sequential step costs a launch whatever the lanes: sequences of a
    # batch that leaves lanes free run as time chunks in both dtypes, every state stored too
    # (the chunks run twice, from the composed starts)
    Row(
        "mean",
        ("euler", "midpoint", "rk4"),
        ("quaternion",),
        None,
        (False, True),
        1,
        MEAN_CHUNK_STEPS,
        "soa_mean_chunked",
        lever=None,
        backends=(ACCELERATOR,),
        max_lanes=MEAN_CHUNK_LANES,
    ),
    # any other batch: one block of few lanes, one compiled kernel (docs/DESIGN.md, "One
    # kernel per block"; XLA's generic scan runs a float64 step as thunks: 13x slower for
    # one trajectory of 1000 samples). On an accelerator the generic kernel's step over all
    # lanes is as fast (float64) or 2x faster (float32, 1024 lanes). On the CPU a long
    # sequence stays here: as time chunks (soa_mean_chunked) one float64 trajectory of 10^5
    # samples ran 59 against 32 M samples/s but compiled in 0.8 against 0.23 s, and at 2^25
    # samples both ran 34 M/s (the chunks' gather is memory-bound)
    Row(
        "mean",
        ("euler", "midpoint", "rk4"),
        LANE_ATTITUDES,
        None,
        (False, True),
        1,
        1,
        "soa_mean",
        rotating=(False, True),
        lever=None,
        backends=(CPU,),
    ),
    # time chunks side by side as lanes, their transitions and noise composed
    # (jaximu/engine/_chunked.py): on the CPU a few long sequences, whose chunks fill a block of
    # lanes; on an accelerator, where a sequential step is a launch, shorter sequences and
    # batches that leave lanes free too
    *(
        Row(
            "covariance",
            ("euler", "midpoint", "rk4"),
            attitudes,
            (jac,),
            (False, True),
            1,
            COV_CHUNK_STEPS[on],
            "soa_cov_chunked",
            rotating=(False, True),
            lever=(False, True),
            backends=(on,),
            max_lanes=COV_CHUNK_LANES[on],
        )
        for on in (CPU, ACCELERATOR)
        for attitudes, jac in ((("quaternion", "matrix"), "analytic"), (LANE_ATTITUDES, "autodiff"))
    ),
    # covariance (final or every step), every scheme, closed-form blocks (Scheme.blocks on the
    # SoA layout; the exact-exponential forms have them); on an accelerator too (2.6-8x the
    # generic kernel on an H100)
    Row(
        "covariance",
        ("euler", "midpoint", "rk4"),
        ("quaternion", "matrix"),
        ("analytic",),
        (False, True),
        1,
        1,
        "soa_cov_analytic",
        rotating=(False, True),
        lever=(False, True),
    ),
    # the same with blocks by autodiff of the SoA step, every attitude form
    Row(
        "covariance",
        ("euler", "midpoint", "rk4"),
        LANE_ATTITUDES,
        ("autodiff",),
        (False, True),
        1,
        1,
        "soa_cov_autodiff",
        rotating=(False, True),
        lever=(False, True),
    ),
    # preintegration, final i→j (min_lanes: see preintegrate_kernel): closed-form blocks or
    # blocks by autodiff of the SoA step (jax.jvp), the same update after them
    Row(
        "preintegrate",
        ("euler",),
        None,
        ("analytic", "autodiff"),
        (False,),
        1,
        1,
        "soa_preint_euler",
        lever=(False, True),
    ),
    Row(
        "preintegrate",
        ("midpoint",),
        None,
        ("analytic", "autodiff"),
        (False,),
        1,
        1,
        "soa_preint_midpoint",
        lever=(False, True),
    ),
)

GENERIC = "generic"

_IMPLEMENTATIONS: dict[tuple[str, str], Callable[..., Any]] = {}


def implements(entry: str, *kernels: str):
    """Register the decorated function as what runs ``entry`` when the table picks one of
    ``kernels``. The engine module that defines an entry registers one function per kernel
    of its rows (and :data:`GENERIC`), each with the entry's own arguments."""

    def register(fn):
        for name in kernels:
            _IMPLEMENTATIONS[(entry, name)] = fn
        return fn

    return register


def implementation(entry, scheme, **options) -> Callable[..., Any]:
    """The function to call for ``entry``: the kernel :func:`kernel` picks for ``scheme`` and
    ``options`` (the same keywords), as its engine module registered it (:func:`implements`)."""
    return _IMPLEMENTATIONS[(entry, kernel(entry, scheme, **options))]


def kernel(
    entry,
    scheme,
    *,
    attitude=None,
    jacobians=None,
    save_all=False,
    lanes=1,
    steps=1,
    dtype="float64",
    fast=True,
    rotating=False,
    lever=False,
    on=None,
) -> str:
    """The kernel that runs ``entry`` for these static options, ``lanes`` batch elements
    and ``steps`` time steps on the backend ``on`` (default :func:`backend`, JAX's default
    backend when the entry is traced); ``rotating``: a world rotation rate
    (``omega_coriolis``) is given (the rows that implement it say so in their ``rotating``
    column); ``lever``: the samples are a sensor's at a lever arm, whose Jacobians couple the
    gyro into the specific force (column "lever arm (Jacobians)" of docs/DESIGN.md)."""
    if not fast:
        return GENERIC
    on = on or backend()
    for row in TABLE:
        if (
            row.entry == entry
            and scheme in row.schemes
            and (row.attitudes is None or attitude in row.attitudes)
            and (row.jacobians is None or jacobians in row.jacobians)
            and save_all in row.save_all
            and lanes >= row.min_lanes
            and (row.max_lanes is None or lanes <= row.max_lanes)
            and steps >= row.min_steps
            and jnp.dtype(dtype).name in row.dtypes
            and rotating in row.rotating
            and (row.lever is None or lever in row.lever)
            and on in row.backends
        ):
            return row.kernel
    return GENERIC


CPU_CHUNK_LANES = 64
"""Lanes the covariance's time chunks fill on the CPU, in either dtype: one trajectory of
10^5 samples, final covariance, ran 11.3–11.5 M samples/s float32 as 64 chunks (128: 10.2,
256: 9.9, 96: 10.9, 32: 10.4) and 5.2–5.4 M float64 (128: 5.0, 32: 5.0), in-process."""


def covariance_chunks(lanes, steps, dtype) -> int:
    """Time chunks per sequence for ``soa_cov_chunked``, each at least
    :data:`MIN_CHUNK_STEPS` steps long: on the CPU enough to fill :data:`CPU_CHUNK_LANES`
    lanes (the chunks run at the batched rate; every chunk more is a step more of the
    composition), on an accelerator :func:`mean_chunks`. ``dtype``: the computation's (the
    same count for both, as measured)."""
    if backend() != CPU:
        return mean_chunks(lanes, steps)
    return int(max(1, min(CPU_CHUNK_LANES // lanes, steps // MIN_CHUNK_STEPS)))


def mean_chunks(lanes, steps) -> int:
    """Time chunks per sequence for ``soa_mean_chunked`` (an accelerator's), each at least
    :data:`MIN_CHUNK_STEPS` steps long, enough to fill :data:`ACCELERATOR_LANES`."""
    return int(max(1, min(-(-ACCELERATOR_LANES // lanes), steps // MIN_CHUNK_STEPS)))


# --------------------------------------------------------------------------- Monte Carlo


class MonteCarloRoute(NamedTuple):
    """How a Monte Carlo study's lane kernel (:mod:`jaximu.kernels.montecarlo_lanes`) runs on
    one kind of device. None of it changes what is computed: run ``i``'s numbers are a
    function of ``(key, i)`` (docs/DESIGN.md section 6), the statistics equal to rounding."""

    chunk_runs: int  # runs (lanes) of one device call: monte_carlo's default chunk_size
    unroll: int  # time steps per iteration of the open-loop study's step loop (lax.scan's)
    filter_unroll: int  # the same for the filter study (each step propagates a covariance)
    rng_loop: bool  # Threefry's rounds in a fori_loop (True) or written out (rng.threefry2x32)


MONTE_CARLO = {
    # The CPU: one chunk per core, each a scan of 2048 lanes (docs/DESIGN.md section 6: the
    # generator measured at 2048 lanes × 1000 steps); XLA:CPU has no multi-output fusion, so
    # the hash's rounds stay a loop whose carry is in memory (written out, every fusion that
    # reads a word recomputes the chain), and a step is one loop iteration.
    CPU: MonteCarloRoute(chunk_runs=2048, unroll=1, filter_unroll=1, rng_loop=True),
    # An accelerator: every loop iteration is a launch and a copy of its predicate to the
    # host. On an NVIDIA H200 the CPU's route ran 10^5 runs × 1000 steps in 23.1 s: 0.47 s a
    # chunk of 2048 runs, 0.47 ms a step, the time of the ~16 loop iterations a step then
    # took (the step's own loop and the hash's two nested loops of rounds), not of the work
    # (3 G samples/s for the engine's mean). So the rounds are written out (one elementwise
    # fusion), a chunk fills the device (2^17 lanes: two ACCELERATOR_LANES blocks, 10^5
    # runs in one call, memory O(chunk · K), 10^6 runs in 8) and each loop iteration of the
    # open-loop study takes 4 steps. The unroll's compile grows faster than the body: this
    # route forced on the 2-core CPU (float32, 40 steps, the test suite's XLA flags, a busy
    # host) compiled its chunk in 4.6 / 5.9 / 6.5 / 24.5 s at 1 / 2 / 4 / 8 steps an
    # iteration; the filter study's step (a covariance too, ten times the operations) keeps
    # one. The chunk and the unrolls are not yet measured on a GPU: benchmarks/accelerator.sh
    # sweeps them (benchmarks/montecarlo.py --sweep).
    ACCELERATOR: MonteCarloRoute(chunk_runs=1 << 17, unroll=4, filter_unroll=1, rng_loop=False),
}
"""The Monte Carlo study's route by backend (:func:`monte_carlo_route`)."""


def monte_carlo_route(on=None) -> MonteCarloRoute:
    """The :class:`MonteCarloRoute` of the backend ``on`` (default :func:`backend`)."""
    return MONTE_CARLO[on or backend()]


# --------------------------------------------------------------------------- preintegration

PREINT_METHODS = ("auto", "sequential", "parallel")


def preint_method(method, lanes, steps, dtype) -> str:
    """``method="auto"``: the fastest correct method for the shape.

    Both methods give the same numbers to rounding. ``"parallel"`` cuts each window into
    time chunks that run side by side as extra lanes; it pays when the batch alone does not
    fill a block of lanes (few, long windows). With enough windows the sequential method
    has all the lanes it needs and does less work.
    """
    if method != "auto":
        return method
    if lanes < _soa.block_lanes(jnp.dtype(dtype)) // 2 and steps >= 4 * MIN_CHUNK:
        return "parallel"
    return "sequential"


def preintegrate_kernel(
    scheme, *, jacobians, prefixes, method, lanes, fast=True, lever=False
) -> str:
    """:func:`kernel` for ``preintegrate``: prefixes (every ``Δ_ik``) have no fast kernel."""
    if prefixes:
        return GENERIC
    return kernel("preintegrate", scheme, jacobians=jacobians, lanes=lanes, fast=fast, lever=lever)


def preintegrate_implementation(scheme, **options) -> Callable[..., Any]:
    """:func:`implementation` for ``preintegrate`` (the options of :func:`preintegrate_kernel`)."""
    return _IMPLEMENTATIONS[("preintegrate", preintegrate_kernel(scheme, **options))]
