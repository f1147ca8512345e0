"""Hyperparameters of the multifidelity GP and their log-space packing for the optimiser."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bams_cli.core.gp._numerics import FloatArray
from bams_cli.core.hyperparameter_values import checked, parsed_dict


@dataclass(frozen=True)
class Hyperparameters:
    """Hyperparameters of the multifidelity GP, in natural (unstandardised) units.

    Attributes
    ----------
    mean : float
        Constant prior mean m.
    outputscale0 : float
        Variance of the theta0 kernel k0.
    lengthscales0 : ndarray of shape (d,)
        Matern lengthscales of k0.
    outputscales : ndarray of shape (L,)
        Variances of the discrepancy kernels k_1..k_L.
    lengthscales : ndarray of shape (L, d)
        Lengthscales of k_1..k_L.
    noise : ndarray of shape (L + 1,)
        Observation noise variance tau_l^2 of each level.
    offsets : ndarray of shape (L,), optional
        Constant bias b_l of level l >= 1 against level 0 (the prior mean of a level-l
        observation is m + b_l); zeros when omitted. A cheap simulator that reads, say,
        0.3 m long everywhere is a constant, not a discrepancy the kernel k_l must learn.
    """

    mean: float
    outputscale0: float
    lengthscales0: FloatArray
    outputscales: FloatArray
    lengthscales: FloatArray
    noise: FloatArray
    offsets: FloatArray | None = None

    def __post_init__(self) -> None:
        values = checked(
            mean=self.mean,
            outputscale0=self.outputscale0,
            lengthscales0=self.lengthscales0,
            outputscales=self.outputscales,
            lengthscales=self.lengthscales,
            noise=self.noise,
            offsets=self.offsets,
        )
        # Frozen means frozen: store float64 copies and make them read-only.
        for name, value in values.items():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def n_levels(self) -> int:
        """Number of levels L + 1."""
        return int(self.noise.size)

    @property
    def d(self) -> int:
        """Input dimension."""
        return int(self.lengthscales0.size)

    # Equality by value; the generated __eq__ would compare arrays with ==, whose truth
    # value is ambiguous. (Hashing raises TypeError: the arrays are unhashable.)
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Hyperparameters):
            return NotImplemented
        return (
            self.mean == other.mean
            and self.outputscale0 == other.outputscale0
            and all(
                np.array_equal(getattr(self, f), getattr(other, f))
                for f in ("lengthscales0", "outputscales", "lengthscales", "noise", "offsets")
            )
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dict (plain floats and lists), natural units."""
        return {
            "mean": float(self.mean),
            "outputscale0": float(self.outputscale0),
            "lengthscales0": self.lengthscales0.tolist(),
            "outputscales": self.outputscales.tolist(),
            "lengthscales": self.lengthscales.tolist(),
            "noise": self.noise.tolist(),
            "offsets": self.offsets.tolist(),  # type: ignore[union-attr]
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Hyperparameters:
        """Inverse of ``to_dict``.

        Parameters
        ----------
        d : dict
            As written by ``to_dict``. ``lengthscales`` may be ``[]`` when L = 0;
            ``offsets`` may be missing (models written before levels had offsets).
        """
        return cls(**parsed_dict(d))  # checked by __post_init__


def _pack(hp: Hyperparameters) -> FloatArray:
    """Log-parameter vector theta of length (L+1)(d+2).

    Layout: [log s_0..s_L, log ell_0..ell_L (row-major, (L+1) x d), log tau_0^2..tau_L^2],
    with s_0 = outputscale0 and ell_0 = lengthscales0. The mean is not in theta (it is
    profiled out).
    """
    s = np.concatenate([[hp.outputscale0], hp.outputscales])
    ell = np.vstack([hp.lengthscales0[None, :], hp.lengthscales])
    with np.errstate(divide="ignore"):  # noise 0 -> -inf, only from fixed hyperparameters
        return np.log(np.concatenate([s, ell.ravel(), hp.noise]))


def _unpack(theta: FloatArray, d: int, n_levels: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of ``_pack`` without the mean: (s (L+1,), ell (L+1, d), noise (L+1,))."""
    p = np.exp(theta)
    m = n_levels
    return p[:m], p[m : m + m * d].reshape(m, d), p[m + m * d :]


def _hyperparameters(
    theta: FloatArray, beta: FloatArray, d: int, n_levels: int, ybar: float, ystd: float
) -> Hyperparameters:
    """Natural-unit Hyperparameters from standardised theta and GLS coefficients.

    ``beta`` = (standardised mean, offset of level 1, ..., offset of level L).
    """
    s, ell, noise = _unpack(theta, d, n_levels)
    v = ystd**2
    return Hyperparameters(
        mean=ybar + ystd * float(beta[0]),
        offsets=ystd * np.asarray(beta[1:], dtype=np.float64),
        outputscale0=float(s[0] * v),
        lengthscales0=ell[0],
        outputscales=s[1:] * v,
        lengthscales=ell[1:],
        noise=noise * v,
    )
