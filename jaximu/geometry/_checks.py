"""Checks at the API boundary: clear ``ValueError``s that name the problem.

Shape checks are static and always run. Value checks (NaN, dt ≤ 0, non-unit quaternion,
a value the computation dtype cannot hold) need concrete numbers, so they run when the
public function is called eagerly and are skipped when its inputs are tracers (inside a
user's ``jit``, ``vmap`` or ``grad``); the user's data is never altered, only read. Eager
calls also check their outputs (:func:`check_output`): finite inputs can still overflow
the dtype (``dt = 1e30`` in float32), and that is reported, never returned as NaN/inf.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.errors import Fix, InputError


def is_concrete(*trees) -> bool:
    """True when no leaf of ``trees`` is a tracer."""
    leaves = jax.tree_util.tree_leaves(trees)
    return not any(isinstance(x, jax.core.Tracer) for x in leaves)


def _index(i) -> str:
    return "[" + ", ".join(str(int(k)) for k in i) + "]"


def _first_bad(mask: np.ndarray) -> str:
    return _index(np.argwhere(mask)[0])


def dtype_kind(d) -> str:
    """numpy's kind letter of the dtype ``d``, with JAX's extra floating types (bfloat16 and
    the float8 family, which numpy files under ``"V"``, raw bytes) as ``"f"``."""
    k = getattr(d, "kind", "O")
    if k == "V":
        try:
            return "f" if jnp.issubdtype(d, jnp.floating) else k
        except TypeError:
            return k
    return k


def _own_kind(x) -> str:
    """:func:`dtype_kind` of ``x``'s own dtype; ``"f"`` for what has none (Python numbers,
    lists: cast later, where they fail by name)."""
    d = getattr(x, "dtype", None)
    return "f" if d is None else dtype_kind(d)


def kind_of(x) -> str:
    """numpy's kind letter of ``x``'s dtype (``"f"``, ``"c"``, ``"b"``, ``"U"``, ...; bfloat16
    ``"f"``): Python scalars and lists by what numpy makes of them; ``"O"`` when it makes
    nothing of them (a ragged list: left to the casts, which name it)."""
    d = getattr(x, "dtype", None)
    if d is None:
        try:
            d = np.asarray(x).dtype
        except (TypeError, ValueError):
            return "O"
    return dtype_kind(d)


def check_real(name: str, x):
    """Refuse a complex ``x`` naming it: a cast to float would drop its imaginary part (numpy
    and JAX only warn)."""
    if not isinstance(x, jax.core.Tracer) and kind_of(x) == "c":
        raise ValueError(
            f"{name} must be real, got a complex value (its imaginary part would "
            f"be dropped); pass {name}.real if that is what you mean"
        )


def _cast(x, dtype, name: str | None = None):
    """``jnp.asarray(x, dtype)`` without numpy's overflow warning (the callers report it).
    With ``name``, an input that is not numbers (``None``, a string, a ragged list) raises a
    ``ValueError`` naming it instead of JAX's own ``TypeError``."""
    if name is not None and not isinstance(x, jax.core.Tracer):
        check_real(name, x)
        if kind_of(x) == "b":  # True is not a 1 s step nor a 1 rad/s rate
            raise ValueError(f"{name} must be an array of numbers, got booleans; pass floats")
    try:
        if name is not None and (isinstance(x, (str, bytes)) or _own_kind(x) in "USOV"):
            raise TypeError("not numbers")  # "0.01" is text, not a step: never parsed for you
        with np.errstate(over="ignore"):
            return jnp.asarray(x, dtype)
    except (TypeError, ValueError):
        if name is None or isinstance(x, jax.core.Tracer):
            raise
        shown = repr(x)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise ValueError(
            f"{name} must be an array of numbers, got {type(x).__name__} {shown}"
        ) from None


def to_dtype(name: str, x, dtype):
    """``x`` as a ``dtype`` array; a concrete finite value that ``dtype`` cannot hold (1e300
    in float32) raises ``ValueError`` naming it instead of becoming inf. NaN and inf inputs
    pass through (:func:`check_finite` reports them)."""
    y = _cast(x, dtype, name)
    if is_concrete(x) and getattr(x, "dtype", None) != y.dtype:
        src = np.asarray(x)
        if dtype_kind(src.dtype) in "fiu":
            with np.errstate(over="ignore"):
                over = np.isfinite(src) & ~np.isfinite(src.astype(y.dtype))
            if over.any():
                i = tuple(np.argwhere(over)[0])
                where = _first_bad(over) if src.ndim else ""
                big = float(jnp.finfo(dtype).max)
                raise ValueError(
                    f"{name}{where} = {float(src[i]):g} is too large for the computation dtype "
                    f"{jnp.dtype(dtype).name} (largest finite value {big:.4g}); rescale it or "
                    "pass float64 inputs (with jax_enable_x64)"
                )
    return y


def check_output(fn_name: str, out, cause: str):
    """Raise ``ValueError`` if a floating leaf of ``out`` holds NaN or inf; returns ``out``.

    The inputs were checked finite, so a non-finite output is an overflow of the
    computation dtype (``cause`` names the likely culprit). Like the value checks this runs
    on eager calls only: it is skipped when ``out`` holds tracers.
    """
    if not is_concrete(out):
        return out
    for path, leaf in jax.tree_util.tree_leaves_with_path(out):
        arr = np.asarray(leaf)
        if not jnp.issubdtype(arr.dtype, jnp.inexact):
            continue
        bad = ~np.isfinite(arr)
        if bad.any():
            where = _first_bad(bad) if arr.ndim else "[]"
            raise ValueError(
                f"{fn_name} produced a non-finite value (NaN or inf) from finite inputs, first in "
                f"output{jax.tree_util.keystr(path)} at index {where}: {cause} for "
                f"{arr.dtype.name}; rescale them"
                + ("" if arr.dtype == np.float64 else " or use float64 (jax_enable_x64)")
            )
    return out


def float_dtype(*xs):
    """The floating dtype of the computation: the promotion of the inputs' dtypes, at least
    float32. Integer inputs and half precision (float16, bfloat16: 3 significant digits,
    which lose every position increment below 1/1000 of the position) are computed in
    float32; the outputs are then float32. The inputs themselves are not changed.

    The callers pass their data (a float64 ``dt``, ``P0`` or ``state.p`` beside float32
    samples makes the computation float64 under ``jax_enable_x64``, as JAX's own promotion
    does: casting it down would lose what the user gave); the model's constants (gravity,
    noise densities, a sensor pose) then take that dtype. The library's records (a
    :class:`jaximu.NavState`, ``ImuBias``: dataclasses) count by their fields; ``None``
    counts for nothing; Python scalars and lists of them are weak (``dt=0.005`` keeps float32
    samples float32)."""

    def numeric(x):  # text, None, ragged lists: left to to_dtype, which names the argument
        if isinstance(x, (int, float)) and not isinstance(x, bool):
            return x  # weakly typed, as in JAX
        if isinstance(x, (list, tuple)):  # Python numbers: weak too (a gravity [0, 0, -9.81])
            try:
                kind = np.asarray(x).dtype.kind
            except (TypeError, ValueError):
                return None
            return 0.0 if kind in "iuf" else None
        try:
            a = x if hasattr(x, "dtype") else np.asarray(x)
        except (TypeError, ValueError):
            return None
        return a if dtype_kind(a.dtype) in "iufc" else None

    leaves = []
    for x in xs:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            leaves.extend(getattr(x, f.name) for f in dataclasses.fields(x))
        elif x is not None:
            leaves.append(x)
    arrays = [a for a in map(numeric, leaves) if a is not None]
    dt = jnp.result_type(*arrays) if arrays else jnp.result_type(jnp.float32)
    if not jnp.issubdtype(dt, jnp.floating) or jnp.dtype(dt).itemsize < 4:
        dt = jnp.result_type(jnp.float32)
    return dt


def check_vector(name: str, x, dim: int = 3, time_axis: bool = True):
    """Shape check for ``(..., T, dim)`` (or ``(..., dim)``)."""
    nd = 2 if time_axis else 1
    want = f"(..., T, {dim})" if time_axis else f"(..., {dim})"
    if x.ndim < nd or x.shape[-1] != dim:
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")


def check_finite(name: str, x, fix: str = ""):
    """On concrete ``x``: a ``ValueError`` naming ``name`` and the first NaN or inf's index
    (and ``fix``, appended) if it holds one."""
    if is_concrete(x):
        arr = np.asarray(x)
        bad = ~np.isfinite(arr)
        if bad.any():
            where = f", first at index {_first_bad(bad)}" if arr.ndim else f": it is {arr}"
            raise ValueError(
                f"{name} contains non-finite values (NaN or inf){where}"
                + (f" ({int(bad.sum())} in all)" if fix and arr.ndim else "")
                + (f"; {fix}" if fix else "")
            )


def check_sign(name: str, x, dtype, *, strict: bool = False, unit: str = "", fix: str = ""):
    """``x`` as a ``dtype`` array (any shape; traced values pass, shape-checked by the
    caller), finite and ``≥ 0`` (``> 0`` with ``strict``) on eager calls; else a
    ``ValueError`` naming ``name``, the first offending value and its index, and ``fix``
    (default: why a sign matters for a standard deviation or a density)."""
    y = to_dtype(name, x, dtype)
    check_finite(name, y, fix or "pass finite numbers")
    if is_concrete(y):
        arr = np.asarray(y)
        bad = ~(arr > 0) if strict else arr < 0
        if bad.any():
            i = tuple(np.argwhere(bad)[0]) if arr.ndim else ()
            where = _first_bad(bad) if arr.ndim else ""
            kind = "positive" if strict else "non-negative"
            raise ValueError(
                f"{name} must be {kind}{f' [{unit}]' if unit else ''}, got {name}{where} = "
                f"{arr[i]:g}; "
                + (
                    fix
                    or "a standard deviation or density is σ ≥ 0, whose sign would be lost in σ²"
                )
            )
    return y


def check_imu(gyro, accel, dt, dtype, allow_intervals=False):
    """Validate measurements and steps; returns ``(gyro, accel, dt, T)`` as ``dtype`` arrays.

    ``gyro``, ``accel``: ``(..., T, 3)``; ``dt``: scalar or ``(..., T)`` (or ``(..., T-1)``
    with ``allow_intervals``), all ``> 0``.
    """
    gyro = to_dtype("gyro", gyro, dtype)
    accel = to_dtype("accel", accel, dtype)
    check_vector("gyro", gyro)
    check_vector("accel", accel)
    T = gyro.shape[-2]
    if accel.shape[-2] != T:
        raise ValueError(
            f"gyro and accel have different numbers of samples: {gyro.shape[-2]} and {accel.shape[-2]}"
        )
    if T < 1:
        raise ValueError("gyro and accel hold no samples (T = 0)")
    dt_in = dt
    dt = _cast(dt, dtype, "dt")
    ok = (T, T - 1) if (allow_intervals and T > 1) else (T,)
    if dt.ndim > 0 and dt.shape[-1] not in ok:
        want = "(..., T) or (..., T-1)" if allow_intervals else "(..., T)"
        raise ValueError(
            f"dt must be a scalar or have shape {want} with T = {T} samples, got {tuple(dt.shape)}"
        )
    check_finite("gyro", gyro)
    check_finite("accel", accel)
    if is_concrete(dt_in):
        arr = np.asarray(dt_in)
        with np.errstate(over="ignore"):
            cast = arr.astype(dt.dtype)
        ok_in = np.isfinite(arr) & (arr > 0)
        ok_cast = np.isfinite(cast) & (cast > 0)  # in float32, 1e300 -> inf and 1e-300 -> 0
        bad = ~ok_in if not ok_in.all() else ~ok_cast
        if bad.any():
            i = tuple(np.argwhere(bad)[0]) if arr.ndim else ()
            where = _first_bad(bad) if arr.ndim else ""
            msg = f"dt must be positive and finite; dt{where} = {arr[i]}"
            if ok_in.all():
                msg += (
                    f", which is {cast[i]} in the computation dtype {cast.dtype.name} (out of "
                    "its range); rescale it or pass float64 inputs (with jax_enable_x64)"
                )
            raise ValueError(msg)
    return _time_whole(gyro, 2), _time_whole(accel, 2), _time_whole(dt, 1), T


def _time_whole(x, n_minor):
    """``x`` with its last ``n_minor`` axes (a sequence's time and component axes) not split
    over devices. The kernels split batch lanes only; a time axis that a user sharded on an
    ``Explicit`` mesh is gathered here, once, so that the slicing along time that every
    kernel does stays valid under sharding in types. Batch axes keep their sharding; arrays
    without a mesh in their type (``Auto`` meshes: the partitioner places them) pass as
    they are."""
    sharding = getattr(jax.typeof(x), "sharding", None)
    mesh, spec = getattr(sharding, "mesh", None), getattr(sharding, "spec", None)
    if mesh is None or mesh.empty or spec is None or x.ndim == 0:
        return x
    spec = tuple(spec) + (None,) * (x.ndim - len(spec))
    if all(s is None for s in spec[x.ndim - n_minor :]):
        return x
    P = jax.sharding.PartitionSpec
    with jax.sharding.use_abstract_mesh(mesh):
        return jax.sharding.reshard(x, P(*spec[: x.ndim - n_minor], *(None,) * n_minor))


def gravity_vector(gravity, dtype):
    """``g_W`` from a magnitude ``g ≥ 0`` (→ ``[0, 0, -g]``) or a ``(..., 3)`` vector (any
    direction). A negative magnitude is refused: it would flip gravity (a still IMU climbing
    at 2 g), and is most often the vector's z component given as the magnitude."""
    g = to_dtype("gravity", gravity, dtype)
    if g.ndim == 0:
        check_finite("gravity", g)
        if is_concrete(g) and float(g) < 0:
            v = float(np.asarray(gravity))
            raise InputError(
                f"gravity = {v:g} is a magnitude, so it must be ≥ 0 (g_W = [0, 0, -g] in the "
                "z-up world)",
                [Fix("gravity", -v)],
                sep=": ",
                api_note=f", or the vector gravity=[0, 0, {-v:g}] if your world's z axis "
                "points down",
            )
        g = jnp.stack([jnp.zeros_like(g), jnp.zeros_like(g), -g])
    elif g.shape[-1] != 3:
        raise ValueError(
            f"gravity must be a magnitude (scalar, g_W = [0, 0, -g]) or a vector (..., 3), got shape {tuple(g.shape)}"
        )
    check_finite("gravity", g)
    return g


def noise_batches(noise):
    """``[(name, batch shape)]`` of the densities of a checked :class:`ImuNoise` (or
    ``None``) that have batch axes (a scalar density has none; a per-axis one ``(..., 3)``),
    named as the user wrote them (``noise.accelerometer_noise_density``), for
    :func:`batch_shape`."""
    if noise is None:
        return []
    return [
        (f"noise.{f.name}", getattr(noise, f.name).shape[:-1])
        for f in dataclasses.fields(noise)
        if jnp.ndim(getattr(noise, f.name))
    ]


def check_key(name: str, key):
    """``key`` if it is one ``jax.random`` key: a typed key array of shape ``()``
    (``jax.random.key(0)``) or a raw ``uint32`` key (``jax.random.PRNGKey(0)``); else a
    ``ValueError`` naming ``name`` (JAX's own error names no argument)."""
    d = getattr(key, "dtype", None)
    if d is not None and jnp.issubdtype(d, jax.dtypes.prng_key):
        if jnp.ndim(key):
            raise ValueError(
                f"{name} must be one jax.random key, got an array of "
                f"{jnp.shape(key)} keys; pass one (jax.vmap over the keys for "
                "several)"
            )
        return key
    if d is not None and d == jnp.uint32 and jnp.ndim(key) == 1:
        return key
    shown = repr(key)
    shown = shown if len(shown) <= 40 else shown[:37] + "..."
    raise ValueError(
        f"{name} must be a jax.random key (e.g. jax.random.key(0)), got "
        f"{type(key).__name__} {shown}"
    )


def check_unbatched_noise(noise, what: str):
    """Refuse batch axes on the densities of a checked :class:`ImuNoise`, naming the
    density: ``what`` (a Monte Carlo study, ...) takes one noise model, scalars or ``(3,)``."""
    for name, shape in noise_batches(noise):
        if shape:
            raise ValueError(
                f"{name} must be a scalar or (3,) for {what} (one noise model), "
                f"got shape {tuple(shape) + (3,)}"
            )


def check_batch_shape(batch_shape, name: str = "batch_shape"):
    """``batch_shape`` as a tuple of non-negative ints; an int ``n`` is refused with the fix
    ``(n,)`` in words (a bare int is not a shape; no command has such an option, so no
    :class:`jaximu.errors.Fix`)."""
    if isinstance(batch_shape, (int, np.integer)) and not isinstance(batch_shape, bool):
        raise ValueError(
            f"{name} must be a tuple of ints, got the int {batch_shape}; "
            f"pass {name}=({int(batch_shape)},)"
        )
    try:
        dims = tuple(batch_shape)
    except TypeError:
        raise ValueError(
            f"{name} must be a tuple of non-negative ints, got "
            f"{type(batch_shape).__name__} {batch_shape!r}"
        ) from None
    for d in dims:
        if isinstance(d, (bool, np.bool_)) or not isinstance(d, (int, np.integer)) or d < 0:
            raise ValueError(f"{name} must be a tuple of non-negative ints, got {batch_shape!r}")
    return tuple(int(d) for d in dims)


def batch_shape(*shapes, names=None, noise=None):
    """The broadcast of the batch ``shapes``; a ``ValueError`` listing them (with ``names``,
    each after its argument's name) when they do not broadcast. ``noise``: a checked
    :class:`ImuNoise` whose densities' batch axes broadcast with them too, each named
    (:func:`noise_batches`)."""
    dens = noise_batches(noise)
    shapes = shapes + tuple(s for _, s in dens)
    if names is not None:
        names = tuple(names) + tuple(n for n, _ in dens)
    try:
        return jnp.broadcast_shapes(*shapes)
    except ValueError:
        listed = (
            [str(tuple(s)) for s in shapes]
            if names is None
            else [f"{n} {tuple(s)}" for n, s in zip(names, shapes)]
        )
        raise ValueError(
            "batch shapes of the inputs do not broadcast: "
            + ", ".join(listed)
            + ("; give them equal leading axes or axes of size 1" if names else "")
        ) from None


# --------------------------------------------------------------------------- scalar options


def check_number(name: str, x) -> float:
    """``x`` as a ``float``: one real number (text, flags and arrays are refused, never
    parsed), naming ``name``."""
    if isinstance(x, (bool, np.bool_, str, bytes)) or np.ndim(x) != 0:  # text: never parsed
        raise ValueError(f"{name} must be a number, got {x!r}")
    try:
        return float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {x!r}") from None


def check_int(name: str, x, minimum: int, what: str | None = None) -> int:
    """``x`` as an ``int`` if it is a whole number ≥ ``minimum`` (``1e4`` is fine, ``1.5``
    and ``True`` are not); else a ``ValueError`` naming ``name``."""
    what = what or (
        "a positive integer"
        if minimum == 1
        else "a non-negative integer"
        if minimum == 0
        else f"an integer ≥ {minimum}"
    )
    try:
        v = check_number(name, x)
    except ValueError:
        raise ValueError(f"{name} must be {what}, got {x!r}") from None
    if not (np.isfinite(v) and v == int(v) and v >= minimum):
        raise ValueError(f"{name} must be {what}, got {x!r}")
    return int(v)


def check_positive(name: str, x, *, allow_zero: bool = False, hint: str = "") -> float:
    """``x`` as a ``float`` if finite and ``> 0`` (``≥ 0`` with ``allow_zero``)."""
    v = check_number(name, x)
    if not (np.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
        kind = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be {kind} and finite, got {x!r}{hint}")
    return v


def check_fraction(name: str, x) -> float:
    """A probability strictly between 0 and 1 (a confidence level)."""
    v = check_number(name, x)
    if not (0.0 < v < 1.0):
        if 1.0 < v < 100.0:
            raise InputError(
                f"{name} must be in (0, 1), got {x!r}",
                [Fix(name, v / 100)],
                lead=f"for {v:g}% pass",
            )
        raise ValueError(f"{name} must be in (0, 1), got {x!r}")
    return v


_WORDS = {
    "true": True,
    "yes": True,
    "on": True,
    "1": True,
    "false": False,
    "no": False,
    "off": False,
    "0": False,
    "none": False,
}


def check_bool(name: str, x) -> bool:
    """``x`` if it is a ``bool`` (or numpy bool). Anything else is refused, since its truth
    value would silently decide the option (``"no"`` is true): a word that says yes or no
    raises :class:`InputError` with the repair, other values a ``ValueError``."""
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, str) and x.strip().lower() in _WORDS:
        v = _WORDS[x.strip().lower()]
        raise InputError(f"{name} must be True or False, got the string {x!r}", [Fix(name, v)])
    if isinstance(x, (int, np.integer)) and x in (0, 1):
        raise InputError(f"{name} must be True or False, got {x!r}", [Fix(name, bool(x))])
    raise ValueError(f"{name} must be True or False, got {type(x).__name__} {x!r}")


def check_choice(name: str, x, choices, what: str | None = None):
    if x not in choices:
        raise ValueError(f"unknown {what or name} {x!r}; choose one of {tuple(choices)}")
    return x


def compute_dtype(name: str, dtype):
    """A user's ``dtype`` option: float32 or float64 (the latter needs ``jax_enable_x64``)."""
    try:
        d = jnp.dtype(dtype)
    except TypeError:
        raise ValueError(
            f"{name} must be a floating dtype (float32 or float64), got {dtype!r}"
        ) from None
    if not jnp.issubdtype(d, jnp.floating) or d.itemsize < 4:
        raise ValueError(f"{name} must be a floating dtype (float32 or float64), got {d.name}")
    if d == jnp.float64 and not jax.config.jax_enable_x64:  # type: ignore[attr-defined]
        raise ValueError(
            f"{name}=float64 needs 64-bit JAX: call "
            "jax.config.update('jax_enable_x64', True) first, or pass float32"
        )
    return d


def as_numbers(name: str, x, dtype=np.float64) -> np.ndarray:
    """``x`` as a numpy array of ``dtype``; text, ``None`` or a ragged list raise a
    ``ValueError`` naming ``name`` (never parsed or guessed for the user), and so does a
    complex one (:func:`check_real`). The callers work on the host, so a JAX tracer (the
    function called inside ``jit``/``vmap``/``grad``) is refused naming ``name`` too."""
    if isinstance(x, jax.core.Tracer):
        raise ValueError(
            f"{name} must be concrete numbers, got a traced value: this function "
            "prepares its inputs on the host with numpy, so call it outside "
            "jax.jit, jax.vmap and jax.grad"
        )
    check_real(name, x)
    kind = _own_kind(x)
    try:
        if x is None or isinstance(x, (str, bytes)) or kind in "USOV":
            raise TypeError
        return np.asarray(x, dtype)
    except (TypeError, ValueError):
        shown = repr(x)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise ValueError(
            f"{name} must be an array of numbers, got {type(x).__name__} {shown}"
        ) from None


TIMES_FIX = "repair the stamps (the readers' sort, drop_duplicates, drop_nonfinite options)"
"""The repair of a recording's bad stamps, as :func:`check_times`'s ``fix``."""


def check_times(name: str, t, minimum: int = 2, fix: str = "") -> np.ndarray:
    """Sample times ``t`` as a float64 numpy array: 1-D, at least ``minimum`` of them,
    finite and strictly increasing (a recording of zero duration, repeated stamps and a NaN
    stamp refused); a ``ValueError`` names ``name``, the first offending index and value,
    and ``fix`` (appended)."""
    arr = as_numbers(name, t)
    tail = f"; {fix}" if fix else ""
    if arr.ndim != 1 or len(arr) < minimum:
        raise ValueError(
            f"{name} must be a 1-D array of at least {minimum} sample times, got shape "
            f"{arr.shape}{tail}"
        )
    check_finite(name, arr, fix)
    step = np.diff(arr)
    if np.any(step <= 0):
        i = int(np.argmax(step <= 0))
        span = f" (all {len(arr)} stamps {arr[0]:g}: zero duration)" if arr[-1] == arr[0] else ""
        raise ValueError(
            f"{name} must increase strictly; {name}[{i + 1}] = {arr[i + 1]:.12g} ≤ "
            f"{name}[{i}] = {arr[i]:.12g}{span}{tail}"
        )
    return arr


def check_array(name: str, x, shape: tuple, fix: str = "pass finite numbers") -> np.ndarray:
    """A concrete numpy array of exactly ``shape``, finite; named in the error (with
    ``fix`` for a NaN or inf)."""
    arr = as_numbers(name, x, None)
    if arr.shape != tuple(shape) or dtype_kind(arr.dtype) not in "fiu":
        raise ValueError(
            f"{name} must have shape {tuple(shape)}, got {arr.shape}"
            if arr.shape != tuple(shape)
            else f"{name} must be numeric, got {arr.dtype}"
        )
    check_finite(name, arr, fix)
    return arr
