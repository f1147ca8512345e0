"""A monotone output transform: model g(y) instead of the metric y.

Failure is y <= gamma, and for any increasing g that is the event g(y) <= g(gamma), so a
model of g(y) gives failure probabilities with the same meaning (DESIGN.md, "The metric's
scale"). A metric that varies by tens of units far from failure and by fractions of one
near it (a minimum gap in metres) is fitted badly by one stationary kernel: the far-away
swings set the output scale and the lengthscales, the misfit lands in the noise and the
discrepancy, and the model is vague exactly where failure is decided. The transform

    g(y) = c + s asinh((y - c) / s),     g'(y) = 1 / sqrt(1 + ((y - c) / s)^2),

is the identity near the centre c (the first gamma; so g(gamma) = gamma and p_n,
``select`` and the estimate need no translation for it) and logarithmic beyond |y - c| ~ s,
which compresses the far-away swings. s = inf is the identity.

The scale is chosen by the data: for each candidate s the GP is fitted by MAP, and the
candidates are compared by the log posterior density of the observed y, i.e. of g(y)
plus the log Jacobian sum_i log g'(y_i) (the change of variables that makes densities of
different transforms comparable; Snelson, Rasmussen and Ghahramani 2004 fit a warp the
same way). Candidates are the identity and s = q x median |y - c| for a few q.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from bams_cli.core.gp._numerics import FloatArray

#: Candidate scales as fractions of the median distance of the observations from c.
SCALE_FRACTIONS = (1.0, 0.25)


@dataclass(frozen=True)
class OutputTransform:
    """g(y) = c + s asinh((y - c) / s); identity when s is inf."""

    centre: float = 0.0
    scale: float = math.inf

    def __post_init__(self) -> None:
        if not (math.isfinite(self.centre) and self.scale > 0 and not math.isnan(self.scale)):
            raise ValueError(
                f"OutputTransform: centre must be finite and scale > 0, got {self.centre}, "
                f"{self.scale}"
            )

    @property
    def is_identity(self) -> bool:
        return math.isinf(self.scale)

    def forward(self, y: Any) -> FloatArray:
        y = np.asarray(y, dtype=np.float64)
        if self.is_identity:
            return y
        return self.centre + self.scale * np.arcsinh((y - self.centre) / self.scale)

    def inverse(self, z: Any) -> FloatArray:
        z = np.asarray(z, dtype=np.float64)
        if self.is_identity:
            return z
        with np.errstate(over="ignore"):
            return self.centre + self.scale * np.sinh((z - self.centre) / self.scale)

    def log_jacobian(self, y: Any) -> float:
        """sum_i log g'(y_i)."""
        if self.is_identity:
            return 0.0
        u = (np.asarray(y, dtype=np.float64) - self.centre) / self.scale
        return float(-0.5 * np.sum(np.log1p(u * u)))

    def to_dict(self) -> dict[str, Any]:
        if self.is_identity:
            return {"kind": "identity"}
        return {"kind": "asinh", "centre": self.centre, "scale": self.scale}

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> OutputTransform:
        """Inverse of ``to_dict``; None (models written before transforms) is the identity."""
        if d is None or d.get("kind", "identity") == "identity":
            return cls()
        if d.get("kind") != "asinh":
            raise ValueError(f"unknown output transform kind {d.get('kind')!r}")
        return cls(centre=float(d["centre"]), scale=float(d["scale"]))


def candidate_transforms(y: FloatArray, centre: float) -> list[OutputTransform]:
    """The identity and asinh at s = q x median |y - c|, q in ``SCALE_FRACTIONS``."""
    out = [OutputTransform(centre=centre)]
    spread = float(np.median(np.abs(np.asarray(y, dtype=np.float64) - centre)))
    if math.isfinite(spread) and spread > 0.0:
        out += [OutputTransform(centre, q * spread) for q in SCALE_FRACTIONS]
    return out
