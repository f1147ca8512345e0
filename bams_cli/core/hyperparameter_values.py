"""The GP's hyperparameters as numbers: shapes and ranges, checked once (numpy only).

``core.gp.Hyperparameters`` checks every instance here, and ``Workspace.read_model``
checks a ``model.json`` here before any command uses it, without loading the GP and scipy
(a ``fit`` with nothing to do must stay fast). A value no fit writes (NaN, a negative
noise, lengthscales for another dimension) is a ``ValueError`` naming the parameter.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Largest sd of the observed values the model accepts: natural-unit variances are
#: sd^2 times standardised ones, and beyond this they overflow a float64.
MAX_SCALE = 1e150


def one_line(a: Any) -> str:
    """An array as one line of at most 8 values: errors are one line, however long ``a``."""
    flat = np.asarray(a, dtype=np.float64).reshape(-1)
    shown = ", ".join(f"{v:.4g}" for v in flat[:8])
    return f"[{shown}{', ...' if flat.size > 8 else ''}] ({flat.size} values)"


def checked(
    *,
    mean: Any,
    outputscale0: Any,
    lengthscales0: Any,
    outputscales: Any,
    lengthscales: Any,
    noise: Any,
    offsets: Any = None,
    scales: Any = None,
) -> dict[str, Any]:
    """The hyperparameters as float64: ``mean`` and ``outputscale0`` floats, the rest
    arrays (lengthscales of shape (L, d), offsets zeros and scales ones when None), or a
    ValueError."""
    ell0 = np.array(lengthscales0, dtype=np.float64).reshape(-1)
    d = ell0.size
    s = np.array(outputscales, dtype=np.float64).reshape(-1)
    ell = np.array(lengthscales, dtype=np.float64)
    if ell.size != s.size * d:
        raise ValueError(
            f"Hyperparameters: lengthscales has shape {ell.shape}, expected (L, d) = "
            f"({s.size}, {d}) from outputscales and lengthscales0"
        )
    ell = ell.reshape(s.size, d)
    noise_ = np.array(noise, dtype=np.float64).reshape(-1)
    if noise_.size != s.size + 1:
        raise ValueError(
            f"Hyperparameters: noise has {noise_.size} entries but outputscales has "
            f"{s.size}; expected one noise variance per level (L + 1 = {s.size + 1})"
        )
    positive = {
        "outputscale0": np.array([outputscale0], dtype=np.float64),
        "lengthscales0": ell0,
        "outputscales": s,
        "lengthscales": ell,
    }
    for name, value in positive.items():
        if not np.all(np.isfinite(value) & (value > 0)):
            raise ValueError(
                f"Hyperparameters: {name} must be finite and > 0, got {one_line(value)}"
            )
    # Noise 0 is allowed for fixed hyperparameters (tests, noise-free what-ifs); the
    # fit never produces it.
    if not np.all(np.isfinite(noise_) & (noise_ >= 0)):
        raise ValueError(f"Hyperparameters: noise must be finite and >= 0, got {one_line(noise_)}")
    offsets_ = (
        np.zeros(s.size) if offsets is None else np.array(offsets, dtype=np.float64).reshape(-1)
    )
    if offsets_.size != s.size or not np.all(np.isfinite(offsets_)):
        raise ValueError(
            f"Hyperparameters: offsets must be {s.size} finite numbers (one per level >= 1), "
            f"got {one_line(offsets_)}"
        )
    if not (math.isfinite(float(mean)) and abs(float(mean)) <= MAX_SCALE):
        raise ValueError(
            f"Hyperparameters: mean must be finite and within +-{MAX_SCALE:g}, got {mean}"
        )
    if np.any(np.abs(offsets_) > MAX_SCALE):
        raise ValueError(f"Hyperparameters: offsets must be within +-{MAX_SCALE:g}")
    scales_ = np.ones(s.size) if scales is None else np.array(scales, dtype=np.float64).reshape(-1)
    if scales_.size != s.size or not np.all(np.isfinite(scales_) & (scales_ > 0)):
        raise ValueError(
            f"Hyperparameters: scales must be {s.size} finite numbers > 0 (one per level "
            f">= 1), got {one_line(scales_)}"
        )
    return {
        "mean": float(mean),
        "outputscale0": float(outputscale0),
        "lengthscales0": ell0,
        "outputscales": s,
        "lengthscales": ell,
        "noise": noise_,
        "offsets": offsets_,
        "scales": scales_,
    }


def parsed_dict(d: dict[str, Any]) -> dict[str, Any]:
    """The arrays of a ``model.json`` ``hyperparameters`` dict (``to_dict``'s layout),
    unchecked: a missing key is a KeyError, a value of another type a TypeError or
    ValueError."""
    s = np.asarray(d["outputscales"], dtype=np.float64)
    ell0 = np.asarray(d["lengthscales0"], dtype=np.float64)
    return {
        "mean": float(d["mean"]),
        "outputscale0": float(d["outputscale0"]),
        "lengthscales0": ell0,
        "outputscales": s,
        "lengthscales": np.asarray(d["lengthscales"], dtype=np.float64).reshape(s.size, ell0.size),
        "noise": np.asarray(d["noise"], dtype=np.float64),
        "offsets": None if d.get("offsets") is None else np.asarray(d["offsets"], np.float64),
        "scales": None if d.get("scales") is None else np.asarray(d["scales"], np.float64),
    }


def checked_dict(d: dict[str, Any]) -> dict[str, Any]:
    """``checked`` on a ``model.json`` ``hyperparameters`` dict (``parsed_dict``)."""
    return checked(**parsed_dict(d))
