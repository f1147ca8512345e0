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
        Constant bias b_l of level l >= 1 against level 0, in level l's units (the prior
        mean of a level-l observation is rho_l m + b_l); zeros when omitted. A cheap
        simulator that reads, say, 0.3 m long everywhere is a constant, not a discrepancy
        the kernel k_l must learn.
    scales : ndarray of shape (L,), optional
        Scale rho_l of level l >= 1 against level 0 (Kennedy and O'Hagan 2000): a level-l
        observation is y_l(x) = rho_l (theta0(x) + delta_l(x) + eps_l) + b_l, so the
        discrepancy delta_l (``outputscales``, ``lengthscales``) and the noise eps_l
        (``noise``) are in level 0's units; ones when omitted (the additive model,
        y_l = theta0 + b_l + delta_l + eps_l). A cheap simulator whose metric reads 2.5
        times level 0's tracks it closely, but differs from it by 1.5 theta0: additively
        that is a large discrepancy, and the cheap level would look weak.
    """

    mean: float
    outputscale0: float
    lengthscales0: FloatArray
    outputscales: FloatArray
    lengthscales: FloatArray
    noise: FloatArray
    offsets: FloatArray | None = None
    scales: FloatArray | None = None

    def __post_init__(self) -> None:
        values = checked(
            mean=self.mean,
            outputscale0=self.outputscale0,
            lengthscales0=self.lengthscales0,
            outputscales=self.outputscales,
            lengthscales=self.lengthscales,
            noise=self.noise,
            offsets=self.offsets,
            scales=self.scales,
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
                for f in (
                    "lengthscales0",
                    "outputscales",
                    "lengthscales",
                    "noise",
                    "offsets",
                    "scales",
                )
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
            "scales": self.scales.tolist(),  # type: ignore[union-attr]
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Hyperparameters:
        """Inverse of ``to_dict``.

        Parameters
        ----------
        d : dict
            As written by ``to_dict``. ``lengthscales`` may be ``[]`` when L = 0;
            ``offsets`` and ``scales`` may be missing (models written before levels had
            them: zeros and ones).
        """
        return cls(**parsed_dict(d))  # checked by __post_init__


def _pack(hp: Hyperparameters) -> FloatArray:
    """Log-parameter vector theta of length (L+1)(d+2) + L.

    Layout: [log s_0..s_L, log ell_0..ell_L (row-major, (L+1) x d), log tau_0^2..tau_L^2,
    log rho_1..rho_L], with s_0 = outputscale0 and ell_0 = lengthscales0. The mean and the
    offsets are not in theta (they are profiled out).
    """
    s = np.concatenate([[hp.outputscale0], hp.outputscales])
    ell = np.vstack([hp.lengthscales0[None, :], hp.lengthscales])
    with np.errstate(divide="ignore"):  # noise 0 -> -inf, only from fixed hyperparameters
        return np.log(np.concatenate([s, ell.ravel(), hp.noise, hp.scales]))  # type: ignore[list-item]


def _unpack(theta: FloatArray, d: int, n_levels: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of ``_pack`` without the mean and the scales: (s (L+1,), ell (L+1, d),
    noise (L+1,))."""
    p = np.exp(theta[: n_levels * (d + 2)])
    m = n_levels
    return p[:m], p[m : m + m * d].reshape(m, d), p[m + m * d :]


def _unpack_scales(theta: FloatArray, d: int, n_levels: int) -> FloatArray:
    """The scales rho_1..rho_L of ``_pack``'s theta, with rho_0 = 1 in front: (L+1,)."""
    return np.concatenate([[1.0], np.exp(theta[n_levels * (d + 2) :])])


def _hyperparameters(
    theta: FloatArray, beta: FloatArray, d: int, n_levels: int, ybar: float, ystd: float
) -> Hyperparameters:
    """Natural-unit Hyperparameters from standardised theta and GLS coefficients.

    ``beta`` = (standardised mean, offset of level 1, ..., offset of level L), fitted to
    level l's values scaled about ybar, ybar + (y_l - ybar) / rho_l (``_MAPObjective``);
    in level l's own units its offset is then rho_l ystd beta_l + (1 - rho_l) ybar.
    """
    s, ell, noise = _unpack(theta, d, n_levels)
    rho = _unpack_scales(theta, d, n_levels)[1:]
    v = ystd**2
    return Hyperparameters(
        mean=ybar + ystd * float(beta[0]),
        offsets=rho * ystd * np.asarray(beta[1:], dtype=np.float64) + (1.0 - rho) * ybar,
        scales=rho,
        outputscale0=float(s[0] * v),
        lengthscales0=ell[0],
        outputscales=s[1:] * v,
        lengthscales=ell[1:],
        noise=noise * v,
    )
