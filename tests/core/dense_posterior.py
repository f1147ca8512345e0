"""A small exact multifidelity GP posterior with fixed hyperparameters, for tests.

Written with plain dense numpy and independently of ``bams_cli.core.gp``: it implements the
``Posterior`` protocol (bams_cli/core/posterior.py) straight from the model in DESIGN.md,

    y = theta0(x) + alpha_l(x) + eps_l,   alpha_0 = 0,   eps_l ~ N(0, tau_l^2),
    k_aug((x, a), (x', b)) = k0(x, x') + [a == b >= 1] k_a(x, x'),

each k a Matern-5/2 ARD kernel with its own output scale. Everything is O(n^3) in the number
of observations and O(n_pool * n) in memory; fine for pools of a few hundred points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

FloatArray = NDArray[np.float64]


def matern52(Xa: FloatArray, Xb: FloatArray, lengthscale: FloatArray, scale: float) -> FloatArray:
    """Matern-5/2 ARD kernel matrix, shape (len(Xa), len(Xb))."""
    A = Xa / lengthscale
    B = Xb / lengthscale
    d2 = (A**2).sum(1)[:, None] + (B**2).sum(1)[None, :] - 2.0 * A @ B.T
    r = np.sqrt(np.maximum(d2, 0.0))
    sr = np.sqrt(5.0) * r
    return scale * (1.0 + sr + 5.0 / 3.0 * r**2) * np.exp(-sr)


@dataclass
class DensePosterior:
    """Exact posterior of the multifidelity GP given observations (x_j, l_j, y_j).

    Parameters
    ----------
    X_obs : ndarray of shape (n, d)
    levels_obs : int ndarray of shape (n,)
    y_obs : ndarray of shape (n,)
    lengthscales : ndarray of shape (L + 1, d)
        Row l is the lengthscale of k_l (row 0: theta0's k0).
    outputscales : ndarray of shape (L + 1,)
    noise : ndarray of shape (L + 1,)
        Noise variances tau_l^2.
    mean : float
        Constant prior mean of theta0 (alpha_l have mean 0).
    """

    X_obs: FloatArray
    levels_obs: NDArray[np.int64]
    y_obs: FloatArray
    lengthscales: FloatArray
    outputscales: FloatArray
    noise: FloatArray
    mean: float = 0.0
    _chol: tuple = field(init=False, repr=False)
    _alpha: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.X_obs = np.atleast_2d(np.asarray(self.X_obs, dtype=np.float64))
        self.levels_obs = np.asarray(self.levels_obs, dtype=np.int64)
        self.y_obs = np.asarray(self.y_obs, dtype=np.float64)
        self.lengthscales = np.atleast_2d(np.asarray(self.lengthscales, dtype=np.float64))
        self.outputscales = np.asarray(self.outputscales, dtype=np.float64)
        self.noise = np.asarray(self.noise, dtype=np.float64)
        K = self.k_aug(self.X_obs, self.levels_obs, self.X_obs, self.levels_obs)
        K[np.diag_indices_from(K)] += self.noise[self.levels_obs]
        self._chol = cho_factor(K, lower=True)
        self._alpha = cho_solve(self._chol, self.y_obs - self.mean)

    # prior kernels -------------------------------------------------------------------
    def k0(self, Xa: FloatArray, Xb: FloatArray) -> FloatArray:
        """Prior covariance of theta0, shape (len(Xa), len(Xb))."""
        return matern52(Xa, Xb, self.lengthscales[0], self.outputscales[0])

    def k_aug(self, Xa, la, Xb, lb) -> FloatArray:
        """Prior covariance of noise-free theta(x, l) = theta0(x) + alpha_l(x)."""
        K = self.k0(Xa, Xb)
        la = np.asarray(la)
        lb = np.asarray(lb)
        for lev in range(1, self.n_levels):
            ia = np.flatnonzero(la == lev)
            ib = np.flatnonzero(lb == lev)
            if len(ia) and len(ib):
                K[np.ix_(ia, ib)] += matern52(
                    Xa[ia], Xb[ib], self.lengthscales[lev], self.outputscales[lev]
                )
        return K

    # Posterior protocol --------------------------------------------------------------
    @property
    def n_levels(self) -> int:
        return len(self.outputscales)

    @property
    def lengthscales0(self) -> FloatArray:
        return self.lengthscales[0]

    def predict_theta0(self, X):
        X = np.asarray(X, dtype=np.float64)
        Ks = self.k0(X, self.X_obs)
        mu = self.mean + Ks @ self._alpha
        v = cho_solve(self._chol, Ks.T)
        sigma2 = self.outputscales[0] - np.einsum("ij,ji->i", Ks, v)
        return mu, np.maximum(sigma2, 0.0)

    def cov_theta0(self, Xa, Xb):
        Ka = self.k0(Xa, self.X_obs)
        Kb = self.k0(Xb, self.X_obs)
        return self.k0(Xa, Xb) - Ka @ cho_solve(self._chol, Kb.T)

    def cov_theta0_obs(self, X, Xc, levels):
        Ka = self.k0(X, self.X_obs)
        Kc = self.k_aug(self.X_obs, self.levels_obs, Xc, levels)
        return self.k0(X, Xc) - Ka @ cho_solve(self._chol, Kc)

    def cov_obs_obs(self, Xa, levels_a, Xb, levels_b, same=None):
        Ka = self.k_aug(Xa, levels_a, self.X_obs, self.levels_obs)
        Kb = self.k_aug(self.X_obs, self.levels_obs, Xb, levels_b)
        G = self.k_aug(Xa, levels_a, Xb, levels_b) - Ka @ cho_solve(self._chol, Kb)
        levels_a = np.asarray(levels_a)
        levels_b = np.asarray(levels_b)
        if same is None:
            same = (np.abs(Xa[:, None, :] - Xb[None, :, :]).max(-1) == 0) & (
                levels_a[:, None] == levels_b[None, :]
            )
        return G + np.where(same, self.noise[levels_a][:, None], 0.0)

    def obs_var(self, Xc, levels):
        levels = np.asarray(levels)
        Kc = self.k_aug(self.X_obs, self.levels_obs, Xc, levels)
        prior = self.outputscales[0] + np.where(
            levels >= 1, self.outputscales[np.maximum(levels, 0)], 0.0
        )
        return prior - np.einsum("ij,ij->j", Kc, cho_solve(self._chol, Kc)) + self.noise[levels]


@dataclass
class Problem:
    """A test problem: pool, posterior, threshold and where the observations sit."""

    posterior: DensePosterior
    X: FloatArray
    gamma: float
    obs_index: NDArray[np.int64]
    obs_level: NDArray[np.int64]

    @property
    def observed_level0(self) -> NDArray[np.bool_]:
        mask = np.zeros(len(self.X), dtype=bool)
        mask[self.obs_index[self.obs_level == 0]] = True
        return mask


def make_problem(
    n_pool: int = 120,
    n_obs: int = 8,
    n_levels: int = 2,
    d: int = 2,
    seed: int = 0,
    noise0: float = 1e-4,
    duplicates: int = 0,
) -> Problem:
    """A random pool, a few observations at pool points and random levels, gamma in the tail.

    ``duplicates`` appends that many exact copies of earlier pool points (real pools have
    repeated segments).
    """
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n_pool - duplicates, d))
    if duplicates:
        X = np.vstack([X, X[rng.choice(len(X), size=duplicates, replace=False)]])
    lengthscales = np.vstack([np.full(d, 1.0), np.full((n_levels - 1, d), 1.5)])
    outputscales = np.array([1.0] + [0.3] * (n_levels - 1))
    noise = np.array([noise0] + [0.05] * (n_levels - 1))
    obs = rng.choice(n_pool - duplicates, size=n_obs, replace=False)
    levels = rng.integers(0, n_levels, size=n_obs)
    f = np.sin(2.0 * X[obs, 0]) + 0.5 * X[obs, 1 % d] ** 2
    y = f + 0.2 * levels + rng.standard_normal(n_obs) * np.sqrt(noise[levels])
    post = DensePosterior(
        X_obs=X[obs],
        levels_obs=levels,
        y_obs=y,
        lengthscales=lengthscales,
        outputscales=outputscales,
        noise=noise,
        mean=0.3,
    )
    return Problem(post, X, 0.0, obs.astype(np.int64), levels.astype(np.int64))
