"""The MAP objective of the multifidelity GP: negative log posterior and its gradient."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_solve
from scipy.linalg.lapack import dpotri

from bams_cli.core.gp._numerics import LOG_2PI, FloatArray, GPFitError, IntArray, cholesky
from bams_cli.core.gp.hyperparameters import _unpack, _unpack_scales
from bams_cli.core.gp.priors import _Priors
from bams_cli.core.kernels import matern52_and_grad_factor

_MAX_DIFF_ELEMENTS = 30_000_000  # cache (n, n, d) squared differences below this size


def mean_basis(levels: IntArray, n_levels: int) -> FloatArray:
    """Design matrix H of the GP's mean: a column of ones, then one indicator per level >= 1.

    Shape (n, n_levels). The offset of level l is identified only if level l and level 0
    both have observations (otherwise its column is, together with the ones, collinear);
    an unidentified level's column is all zeros and its offset stays 0.
    """
    levels = np.asarray(levels)
    H = np.zeros((levels.size, n_levels))
    H[:, 0] = 1.0
    if not np.any(levels == 0):
        return H
    for lv in range(1, n_levels):
        H[:, lv] = levels == lv
    return H


class _SquaredDiffs:
    """Per-dimension squared differences of the training inputs, D[a, b, j] = (x_aj - x_bj)^2.

    Cached as an (n*n, d) array when small (two BLAS matrix-vector products per objective
    evaluation), recomputed dimension by dimension otherwise (no n x n x d memory).
    """

    def __init__(self, X: FloatArray) -> None:
        self.n, self.d = X.shape
        self._X = X
        self._flat: FloatArray | None = None
        if self.n * self.n * self.d <= _MAX_DIFF_ELEMENTS:
            self._flat = ((X[:, None, :] - X[None, :, :]) ** 2).reshape(-1, self.d)

    def weighted(self, w: FloatArray) -> FloatArray:
        """sum_j w_j D[:, :, j], shape (n, n)."""
        if self._flat is not None:
            return (self._flat @ w).reshape(self.n, self.n)
        out = np.zeros((self.n, self.n))
        for j in range(self.d):
            diff = self._X[:, j, None] - self._X[None, :, j]
            out += w[j] * diff * diff
        return out

    def contract(self, M: FloatArray) -> FloatArray:
        """sum_ab M[a, b] D[a, b, j] for every j, shape (d,)."""
        if self._flat is not None:
            return M.ravel() @ self._flat
        out = np.empty(self.d)
        for j in range(self.d):
            diff = self._X[:, j, None] - self._X[None, :, j]
            out[j] = np.sum(M * diff * diff)
        return out


class _MAPObjective:
    """Negative log posterior of standardised-unit theta, with its analytic gradient.

    f(theta) = -log N(y | H beta_hat, K) - log p(theta), with beta_hat the GLS mean and
    level offsets (``mean_basis``); by the envelope theorem the gradient of the profiled
    objective is the usual one at beta_hat. Gradient
    (GPML eq. 5.9, with K^-1 from the Cholesky factor):
    d(-log N)/dtheta_i = 1/2 tr((K^-1 - alpha alpha^T) dK/dtheta_i), alpha = K^-1 (y - H beta_hat).
    Each trace is an elementwise sum (both matrices symmetric), and all lengthscale traces
    of one kernel come from one contraction with the cached squared differences
    (``kernels`` module docstring for dk/dlog ell_j), so one evaluation costs one Cholesky,
    one inverse and O(n^2 d).

    A cheap level's scale rho_l (``Hyperparameters.scales``) enters through the data: its
    values are scaled about the standardised mean 0, y'_i = y_i / rho_l, and the additive
    model is fitted to y', whose density is y's times the Jacobian prod rho_l^(n_l). So
    f gains sum_l n_l log rho_l, and by the envelope theorem again
    d f / d log rho_l = n_l - sum_{i at level l} alpha_i y'_i.

    Parameters
    ----------
    X : ndarray of shape (n, d)
    levels : int ndarray of shape (n,)
    y : ndarray of shape (n,)
        Standardised outputs.
    n_levels : int
    priors : _Priors
    """

    def __init__(
        self, X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int, priors: _Priors
    ) -> None:
        self.n, self.d = X.shape
        self.n_levels = n_levels
        self.levels = levels
        self.y = y
        self.H = mean_basis(levels, n_levels)
        self._n_per_level = np.bincount(levels, minlength=n_levels).astype(np.float64)
        self.priors = priors
        self.idx = [np.flatnonzero(levels == lv) for lv in range(n_levels)]
        self.diffs = [_SquaredDiffs(X)] + [
            _SquaredDiffs(X[self.idx[lv]]) for lv in range(1, n_levels)
        ]

    def covariance(self, theta: FloatArray) -> tuple[FloatArray, list, FloatArray]:
        """K (n, n), per-kernel (K_l, G_l) blocks, and per-observation noise (n,)."""
        s, ell, noise = _unpack(theta, self.d, self.n_levels)
        # weights 5 / ell^2 give z^2 = 5 r^2 directly (kernels.matern52_and_grad_factor)
        K0, G0 = matern52_and_grad_factor(self.diffs[0].weighted(5.0 / ell[0] ** 2), s[0])
        K = K0.copy()
        parts = [(K0, G0)]
        for lv in range(1, self.n_levels):
            idx = self.idx[lv]
            Kl, Gl = matern52_and_grad_factor(self.diffs[lv].weighted(5.0 / ell[lv] ** 2), s[lv])
            K[np.ix_(idx, idx)] += Kl
            parts.append((Kl, Gl))
        tau2 = noise[self.levels]
        K[np.diag_indices_from(K)] += tau2
        return K, parts, tau2

    def scaled_y(self, theta: FloatArray) -> FloatArray:
        """y' = y / rho_l at each level-l observation (rho_0 = 1; class docstring)."""
        rho = _unpack_scales(theta, self.d, self.n_levels)
        return self.y / rho[self.levels]

    def gls_mean(self, L: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """GLS coefficients beta = (H'K^-1 H)^-1 H'K^-1 y and alpha = K^-1 (y - H beta).

        ``y`` is ``scaled_y(theta)``. beta has length n_levels: the constant mean, then
        each level's offset (0 for a level whose offset the data cannot identify,
        ``mean_basis``).
        """
        sol = cho_solve((L, True), np.column_stack([self.H, y]), check_finite=False)
        Kinv_H, Kinv_y = sol[:, :-1], sol[:, -1]
        A = self.H.T @ Kinv_H
        keep = np.flatnonzero(np.any(self.H != 0.0, axis=0))
        beta = np.zeros(self.H.shape[1])
        beta[keep] = np.linalg.solve(A[np.ix_(keep, keep)], self.H[:, keep].T @ Kinv_y)
        return beta, Kinv_y - Kinv_H @ beta

    def __call__(self, theta: FloatArray) -> tuple[float, FloatArray]:
        """f(theta) and df/dtheta, shape (len(theta),)."""
        s, ell, noise = _unpack(theta, self.d, self.n_levels)
        K, parts, _ = self.covariance(theta)
        try:
            L, _ = cholesky(K)
        except GPFitError:
            # Only reachable through overflow at extreme bounds; L-BFGS-B backtracks.
            return math.inf, np.zeros_like(theta)
        y = self.scaled_y(theta)
        beta, alpha = self.gls_mean(L, y)
        r = y - self.H @ beta
        m_ = self.n_levels
        log_rho = theta[m_ * (self.d + 2) :]
        nll = (
            0.5 * float(r @ alpha)
            + float(np.sum(np.log(np.diag(L))))
            + 0.5 * self.n * LOG_2PI
            + float(self._n_per_level[1:] @ log_rho)
        )
        # d nll / dtheta_i = 1/2 sum(W * dK_i), W = K^-1 - alpha alpha^T. LAPACK potri
        # inverts from the Cholesky factor in 2n^3/3 flops (cho_solve against I costs 2n^3)
        # but fills only the lower triangle T. Rather than symmetrise, use that every dK_i
        # is symmetric: with W' = 2 T - alpha alpha^T,
        #   sum(W * A) = sum(W' * A) - sum(diag(T) diag(A)),
        # and for the lengthscales (D_j has a zero diagonal) the contraction of W' * G
        # equals that of W * G. A level block W[idx, idx] keeps this form: idx is sorted,
        # so T[idx, idx] is lower triangular too.
        Kinv, info = dpotri(L, lower=1)
        if info != 0:
            return math.inf, np.zeros_like(theta)
        diag_Kinv = np.diag(Kinv).copy()
        W = np.tril(Kinv)
        W *= 2.0
        W -= np.outer(alpha, alpha)

        grad = np.empty_like(theta)
        ell_grad = np.empty((m_, self.d))
        for lv, (Kl, Gl) in enumerate(parts):
            idx = self.idx[lv]
            Wl = W if lv == 0 else W[np.ix_(idx, idx)]
            trace_T = diag_Kinv.sum() if lv == 0 else diag_Kinv[idx].sum()
            grad[lv] = 0.5 * (np.sum(Wl * Kl) - s[lv] * trace_T)  # dK/dlog s_l = K_l
            Gl *= Wl
            ell_grad[lv] = 0.5 * self.diffs[lv].contract(Gl) / ell[lv] ** 2
        grad[m_ : m_ + m_ * self.d] = ell_grad.ravel()
        # dK/dlog tau_l^2 = tau_l^2 on level-l diagonal entries; diag(W) = diag(T) - alpha^2.
        grad[m_ + m_ * self.d : m_ * (self.d + 2)] = (
            0.5 * noise * np.bincount(self.levels, weights=diag_Kinv - alpha**2, minlength=m_)
        )
        # d f / d log rho_l = n_l - sum_{level l} alpha_i y'_i (class docstring)
        grad[m_ * (self.d + 2) :] = (
            self._n_per_level[1:] - np.bincount(self.levels, weights=alpha * y, minlength=m_)[1:]
        )

        lp, lp_grad = self.priors.log_prior(theta)
        return nll - lp, grad - lp_grad
