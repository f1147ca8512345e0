"""The BAMS acquisition: forward-looking point variance beta and its pool average J.

Paper section 3 ("Acquisition function") and appendix A.2, in the form DESIGN.md settles:
with s(x) = (gamma - mu_n(x)) / sigma_n(x) and t(x) = sigma_{n+S}^2(x) / sigma_n^2(x) the
fraction of theta0's variance at x that a batch S of future observations leaves,

    beta_n(x; S) = Phi2(s, -s; rho = t - 1) = 2 T(s, sqrt(t / (2 - t))),    (paper eq. (3))

T being Owen's T function. beta(t = 1) = h_n = p_n (1 - p_n), beta(t = 0) = 0, and beta is
increasing and concave in t:

    d beta / dt = exp(-s^2 / (2 - t)) / (2 pi sqrt(t (2 - t))),

positive and decreasing on (0, 1]. J(S) is the pool mean of beta.

The selection loop evaluates beta for every (pool row, candidate) pair, ~1e8 values per pick
at N = 45k. For that it uses a per-row Chebyshev fit (``fit_beta_chebyshev``) with an
a-posteriori error bound; the exact value always comes from ``beta``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr, owens_t

FloatArray = NDArray[np.float64]

#: Degree of the per-row polynomial used to screen candidates (see ``fit_beta_chebyshev``);
#: ``select._update_and_screen`` is written out for exactly this degree.
CHEB_DEGREE = 8
#: Number of Chebyshev nodes the fit interpolates at; coefficients above CHEB_DEGREE bound the
#: truncation error.
CHEB_NODES = 33


def margin(mu: ArrayLike, sigma2: ArrayLike, gamma: float) -> FloatArray:
    """Standardised margin s = (gamma - mu_n) / sigma_n (paper appendix A.2, s-hat).

    Where sigma_n^2 = 0, theta0 is known: s = +inf if mu <= gamma (p = 1) else -inf (p = 0),
    so that ``point_variance`` and ``beta`` both give exactly 0 there.

    Parameters
    ----------
    mu : array_like of shape (n,)
    sigma2 : array_like of shape (n,)
    gamma : float

    Returns
    -------
    s : ndarray of shape (n,)
    """
    mu = np.asarray(mu, dtype=np.float64)
    sigma2 = np.asarray(sigma2, dtype=np.float64)
    known = sigma2 <= 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (gamma - mu) / np.sqrt(np.where(known, 1.0, sigma2))
    return np.where(known, np.where(mu <= gamma, np.inf, -np.inf), s)


def point_variance(s: ArrayLike) -> FloatArray:
    """h_n = p_n (1 - p_n) with p_n = Phi(s) (paper section 3, point-variance function).

    Written as Phi(s) Phi(-s) so that neither factor is a cancelling 1 - p.

    Parameters
    ----------
    s : array_like of shape (n,)

    Returns
    -------
    h : ndarray of shape (n,)
    """
    s = np.asarray(s, dtype=np.float64)
    return ndtr(s) * ndtr(-s)


def beta(s: ArrayLike, t: ArrayLike) -> FloatArray:
    """Forward-looking point variance beta(s, t) = 2 T(s, sqrt(t / (2 - t))) (appendix A.2).

    Equal to the bivariate normal probability Phi2(s, -s; rho = t - 1). ``t`` is clipped into
    [0, 1]: rounding in sigma_{n+S}^2 = sigma_n^2 - (explained variance) can land it just
    outside.

    Parameters
    ----------
    s : array_like, broadcastable with t
        Standardised margin (gamma - mu_n) / sigma_n.
    t : array_like, broadcastable with s
        Remaining-variance fraction sigma_{n+S}^2 / sigma_n^2.

    Returns
    -------
    beta : ndarray of the broadcast shape, values in [0, 1/4]
    """
    s = np.asarray(s, dtype=np.float64)
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return 2.0 * owens_t(s, np.sqrt(t / (2.0 - t)))


def acquisition_j(s: ArrayLike, t: ArrayLike | None = None) -> float:
    """J(S) = pool mean of beta(s, t) (paper eq. (4)); J(empty) = mean h_n when t is None.

    Parameters
    ----------
    s : array_like of shape (n,)
    t : array_like of shape (n,), optional
        Remaining-variance fractions after the batch; None means no batch (t = 1).

    Returns
    -------
    J : float
    """
    if t is None:
        return float(np.mean(point_variance(s)))
    return float(np.mean(beta(s, t)))


def remaining_fraction(sigma2: ArrayLike, sigma2_after: ArrayLike) -> FloatArray:
    """t = sigma_{n+S}^2 / sigma_n^2, clipped into [0, 1]; 1 where sigma_n^2 = 0.

    Parameters
    ----------
    sigma2 : array_like of shape (n,)
    sigma2_after : array_like of shape (n,)

    Returns
    -------
    t : ndarray of shape (n,)
    """
    sigma2 = np.asarray(sigma2, dtype=np.float64)
    sigma2_after = np.asarray(sigma2_after, dtype=np.float64)
    pos = sigma2 > 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(pos, sigma2_after / np.where(pos, sigma2, 1.0), 1.0)
    return np.clip(t, 0.0, 1.0)


def _cheb_nodes(n_nodes: int) -> FloatArray:
    """Chebyshev points of the first kind in (-1, 1), shape (n_nodes,), in DCT-II order."""
    k = np.arange(n_nodes)
    return np.cos(np.pi * (k + 0.5) / n_nodes)


def fit_beta_chebyshev(
    s: ArrayLike, degree: int = CHEB_DEGREE, n_nodes: int = CHEB_NODES
) -> tuple[FloatArray, FloatArray]:
    """Per-row polynomial for beta(s_x, .) on t in [0, 1], with an error bound.

    beta(s, t) is an odd analytic function of u = sqrt(t) (T(s, a) is odd in a and
    a = u / sqrt(2 - u^2)), so beta(s, t) = sqrt(t) g_s(t) with g_s analytic on [0, 1]. We
    interpolate g_s at ``n_nodes`` Chebyshev points of t and keep the first ``degree + 1``
    coefficients. The bound

        |beta(s, t) - sqrt(t) P_s(t)| <= err = 2 sum_{k > degree} |a_k| + 64 eps sum_k |a_k|

    is the usual a-posteriori Chebyshev tail bound (the factor 2 covers the aliasing of the
    interpolant, the eps term the rounding of the Clenshaw recurrence). The default degree 8
    reproduces beta to ~5e-9 h_n for |s| <= 3 and ~1e-4 h_n at |s| = 7 (measured; degree 16
    gives ~1e-14 h_n but costs 1.5x more in the selection loop). The polynomial only screens
    candidates in ``select``: its error widens the screening slack, never the answer.

    Parameters
    ----------
    s : array_like of shape (n,)
        Finite standardised margins.
    degree : int
    n_nodes : int
        Must exceed ``degree``.

    Returns
    -------
    coef : ndarray of shape (n, degree + 1)
        Chebyshev coefficients of g_s in the variable z = 2 t - 1.
    err : ndarray of shape (n,)
        Bound on the absolute error of sqrt(t) * P_s(t) against beta(s, t) on [0, 1].
    """
    if n_nodes <= degree:
        raise ValueError(f"n_nodes must exceed degree; got n_nodes={n_nodes}, degree={degree}")
    s = np.asarray(s, dtype=np.float64)
    z = _cheb_nodes(n_nodes)
    t = 0.5 * (z + 1.0)  # nodes avoid t = 0, where g_s is the limit beta / sqrt(t)
    vals = beta(s[:, None], t[None, :]) / np.sqrt(t)[None, :]
    # DCT-II: a_k = (2 / n) sum_j g(z_j) T_k(z_j), a_0 halved.
    k = np.arange(n_nodes)
    Tkj = np.cos(np.outer(k, np.pi * (k + 0.5) / n_nodes))
    a = vals @ Tkj.T * (2.0 / n_nodes)
    a[:, 0] *= 0.5
    tail = np.abs(a[:, degree + 1 :]).sum(axis=1)
    err = 2.0 * tail + 64.0 * np.finfo(np.float64).eps * np.abs(a).sum(axis=1)
    return np.ascontiguousarray(a[:, : degree + 1]), err


def beta_poly(s: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Monomial form of ``fit_beta_chebyshev`` for a compiled loop, with its total error bound.

    Returns m with sqrt(t) * sum_j m_j z^j ~= beta(s, t), z = 2 t - 1, and a bound on
    |beta(s, t) - sqrt(t) sum_j m_j z^j| as evaluated in float64 (Estrin's scheme, no fused
    multiply-add) for every t in [0, 1]. On top of the Chebyshev tail bound it adds

    - the rounding of the basis change m = a @ M, M[k, j] = coefficient of z^j in T_k (exact
      integers): <= gamma_17 sum_k |a_k| ||T_k||_1, gamma_n = n eps / (1 - n eps);
    - the rounding of the evaluation, of z = 2 t - 1 (times the Markov bound deg^2 on P')
      and of sqrt(t): <= 400 eps sum_j |m_j|.

    For the smooth functions at hand the change of basis costs nothing: sum |m_j| is within
    1% of sum |a_k| for every |s| <= 8, so the monomial form is as accurate as Clenshaw
    while Estrin's evaluation has depth 4 instead of 8 (the loop is latency-bound otherwise).

    Parameters
    ----------
    s : array_like of shape (n,)

    Returns
    -------
    m : ndarray of shape (n, CHEB_DEGREE + 1)
    err : ndarray of shape (n,)
    """
    a, err = fit_beta_chebyshev(s)
    M = _cheb_to_monomial(a.shape[1] - 1)
    m = a @ M
    eps = np.finfo(np.float64).eps
    n = a.shape[1]
    gamma_n = n * eps / (1.0 - n * eps)
    err = err + gamma_n * (np.abs(a) @ np.abs(M).sum(axis=1)) + 400.0 * eps * np.abs(m).sum(1)
    return np.ascontiguousarray(m), err


def _cheb_to_monomial(degree: int) -> FloatArray:
    """M of shape (degree + 1, degree + 1), row k = monomial coefficients of T_k."""
    M = np.zeros((degree + 1, degree + 1))
    M[0, 0] = 1.0
    if degree >= 1:
        M[1, 1] = 1.0
    for k in range(2, degree + 1):
        # T_k = 2 z T_{k-1} - T_{k-2}; integer coefficients, exact in float64 for k <= 50.
        M[k, 1:] = 2.0 * M[k - 1, :-1]
        M[k] -= M[k - 2]
    return M


def eval_beta_poly(m: FloatArray, t: ArrayLike) -> FloatArray:
    """Evaluate sqrt(t) sum_j m_j (2 t - 1)^j row by row (numpy reference, for tests).

    Parameters
    ----------
    m : ndarray of shape (n, degree + 1)
    t : array_like of shape (n, k)

    Returns
    -------
    beta_approx : ndarray of shape (n, k)
    """
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    z = 2.0 * t - 1.0
    acc = np.zeros_like(z) + m[:, -1:]
    for j in range(m.shape[1] - 2, -1, -1):
        acc = acc * z + m[:, j : j + 1]
    return np.sqrt(t) * acc
