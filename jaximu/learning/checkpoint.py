"""Saving and loading a trained model: a folder with ``model.json`` (format, settings,
training record) and ``weights.eqx`` (equinox's leaf serialisation, float32).

A model written on one machine loads on another: the settings rebuild the network's
structure, and the weights fill it.
"""

from __future__ import annotations

import json
import os
import pathlib

import equinox as eqx
import jax

from jaximu.io import DataError
from jaximu.learning.model import Denoiser, ModelConfig, check_model, check_weights

__all__ = ["save", "load", "weights", "pretrained", "shipped", "FORMAT", "PRETRAINED"]

FORMAT = "jaximu.learning.Denoiser/2"
"""The model file format; a folder of another format is refused by :func:`load`."""

PRETRAINED = {
    name: pathlib.Path(__file__).parent / "pretrained" / name for name in ("euroc", "tumvi")
}
"""Models shipped with the package, by name."""


def save(path, model: Denoiser, record: dict | None = None) -> pathlib.Path:
    """Write ``model`` to the folder ``path`` (created; its two files replaced). A model
    whose weights are not finite (a diverged training) is refused before anything is
    written."""
    check_model("model", model)
    path = pathlib.Path(path)
    if path.exists() and not path.is_dir():
        raise DataError(f"{path} is a file; a model is saved as a folder: give a new name")
    path.mkdir(parents=True, exist_ok=True)
    meta = {"format": FORMAT, "config": model.config.to_json(), "record": record or {}}
    tmp = path / "weights.eqx.tmp"
    eqx.tree_serialise_leaves(tmp, weights(model))
    tmp.replace(path / "weights.eqx")
    (path / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
    return path


def load(path) -> Denoiser:
    """Read a model folder written by :func:`save` (or a name of :data:`PRETRAINED`).

    A model folder that exists under a shipped model's name (``jaximu learn train --out
    euroc``, as the shipped model's own record has it) is the one read: a path the user
    wrote wins over the name; :func:`pretrained` reads the shipped one always.

    Raises:
        DataError: not a model folder, another format or version, damaged weights.
    """
    if shipped(path):
        return pretrained(path)
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(
            f"path must be a model folder (a str or path) or a shipped model's name "
            f"({', '.join(PRETRAINED)}), got {type(path).__name__} {path!r}"
        )
    path = pathlib.Path(path)
    meta_path, weights_path = path / "model.json", path / "weights.eqx"
    if not path.is_dir() or not meta_path.is_file() or not weights_path.is_file():
        raise DataError(
            f"{path} is not a jaximu model: expected a folder with model.json and "
            "weights.eqx, as `jaximu learn train --out MODEL` writes (or the name "
            f"of a shipped model: {', '.join(PRETRAINED)})"
        )
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{meta_path} is not valid JSON ({e}); the model is damaged") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else None
        raise DataError(
            f"{path} holds a model of format {found!r}; this jaximu reads {FORMAT!r}:"
            " retrain it with this version (`jaximu learn train`)"
        )
    try:
        config = ModelConfig.from_json(meta["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(
            f"{meta_path}: its settings do not fit this jaximu ({e}); retrain the "
            "model with this version"
        ) from None
    skeleton = Denoiser(config, jax.random.key(0))
    try:
        model = eqx.combine(eqx.tree_deserialise_leaves(weights_path, weights(skeleton)), skeleton)
    except Exception as e:  # equinox raises RuntimeError/ValueError/EOFError on a bad file
        raise DataError(
            f"{weights_path} does not hold this model's weights ({type(e).__name__}: "
            f"{e}); the file is damaged or from another model"
        ) from None
    try:
        check_weights("model", model)
    except ValueError as e:
        raise DataError(f"{weights_path}: {e}") from None
    return model


def weights(model: Denoiser) -> Denoiser:
    """``model`` without its fitted settings (``model.fitted``, which ``model.json``
    holds): what ``weights.eqx`` stores, leaf for leaf."""
    return eqx.tree_at(lambda m: m.fitted, model, replace_fn=lambda _: None)


def shipped(path) -> bool:
    """Whether :func:`load` reads ``path`` as a shipped model: a name of :data:`PRETRAINED`
    with no model folder of that name here."""
    return (
        isinstance(path, str)
        and path in PRETRAINED
        and not (pathlib.Path(path) / "model.json").is_file()
    )


def record(path) -> dict:
    """The training record saved beside a model (command, seed, data, figures)."""
    if shipped(path):
        path = PRETRAINED[path]
    return json.loads((pathlib.Path(path) / "model.json").read_text()).get("record", {})


def pretrained(name: str = "euroc") -> Denoiser:
    """A model shipped with the package: ``"euroc"``, trained on the EuRoC MAV training
    sequences (ADIS16448 at 200 Hz), or ``"tumvi"``, trained on TUM-VI's rooms 1, 3 and 5
    (BMI160, 512_16 export, about 200 Hz); each ``model.json`` records the command, seed
    and data."""
    if name not in PRETRAINED:
        raise ValueError(f"unknown pretrained model {name!r}; choose one of {sorted(PRETRAINED)}")
    return load(PRETRAINED[name])
