"""The GP's own failure-rate estimate and its exact variance (paper section 3, appendix B.1).

p_hat_GP = mean(p_n), with Var(p_hat_GP) = (1/N^2) sum_ij [Phi2(s_i, s_j; r_ij) - p_i p_j]
(``gp_variance_exact``) and the bound Var <= mean(p_n (1 - p_n)) (Proposition 1,
``gp_estimate``). Split from ``core.estimate``, which keeps the importance-sampling
estimate and re-exports these names.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def gp_estimate(p: ArrayLike) -> tuple[float, float]:
    """GP estimate mean(p_n) and its Proposition-1 bound mean(p_n (1 - p_n)).

    Parameters
    ----------
    p : array_like of shape (n_pool,)

    Returns
    -------
    p_hat : float
        E[p_hat_GP] = mean(p_n) (paper section 3).
    var_bound : float
        Var(p_hat_GP) <= mean(p_n (1 - p_n)) (paper Proposition 1, appendix B.2).
    """
    p = np.asarray(p, dtype=np.float64)
    return float(p.mean()), float(np.mean(p * (1.0 - p)))


@dataclass(frozen=True)
class GPVariance:
    """Result of ``gp_variance_exact``.

    Attributes
    ----------
    var : float
        (1/N^2) sum over kept pairs of cov(g_i, g_j), diagonal over every unit.
    skipped_bound : float
        Bound on |Var - var| from the skipped pairs (Cauchy-Schwarz, |cov| <= sqrt(h_i h_j)).
    h_mean : float
        mean(p (1 - p)), the Proposition-1 upper bound on Var.
    n_kept : int
        Units whose pairs were computed (h_i >= h_tol).
    """

    var: float
    skipped_bound: float
    h_mean: float
    n_kept: int


# Gauss-Legendre rules of Genz (2004) on [-1, 1]: 6, 12 and 20 points.
_GL = [np.polynomial.legendre.leggauss(n) for n in (6, 12, 20)]
_GL_X = np.zeros((3, 20))
_GL_W = np.zeros((3, 20))
for _k, (_x, _w) in enumerate(_GL):
    _GL_X[_k, : _x.size] = _x
    _GL_W[_k, : _w.size] = _w
_TWOPI = 2.0 * math.pi


@numba.njit(cache=True)
def _phi(x: float) -> float:
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


@numba.njit(cache=True)
def _bvn_cov(h: float, k: float, r: float, glx: FloatArray, glw: FloatArray) -> float:
    """Phi2(h, k; r) - Phi(h) Phi(k) for finite h, k and |r| <= 1 (Genz 2004, BVNU).

    For |r| < 0.925 this is Plackett's integral taken directly,
        (1/2 pi) int_0^asin(r) exp(-(h^2 + k^2 - 2 h k sin t) / (2 cos^2 t)) dt,
    by Gauss-Legendre (6/12/20 points as |r| grows), so the covariance never comes from a
    difference of two nearly equal probabilities. For |r| >= 0.925 Genz's expansion about
    r = +-1 gives the orthant probability itself and we subtract Phi(h) Phi(k). Absolute
    accuracy ~1e-15 throughout (Genz 2004, Stat. Comput. 14:251).
    """
    ar = abs(r)
    if ar < 0.3:
        g = 0
    elif ar < 0.75:
        g = 1
    else:
        g = 2
    ng = 6 if g == 0 else (12 if g == 1 else 20)
    if ar < 0.925:
        hs = 0.5 * (h * h + k * k)
        hk = h * k
        asr = math.asin(r)
        acc = 0.0
        for i in range(ng):
            sn = math.sin(0.5 * asr * (1.0 + glx[g, i]))
            acc += glw[g, i] * math.exp((sn * hk - hs) / (1.0 - sn * sn))
        return acc * asr / (2.0 * _TWOPI)
    # Upper orthant P(X > -h, Y > -k) = Phi2(h, k; r), by Genz's large-|r| branch.
    dh = -h
    dk = -k
    if r < 0.0:
        dk = -dk
    hk = dh * dk
    bvn = 0.0
    if ar < 1.0:
        as_ = (1.0 - r) * (1.0 + r)
        a = math.sqrt(as_)
        bs = (dh - dk) ** 2
        c = (4.0 - hk) / 8.0
        d = (12.0 - hk) / 16.0
        asr = -(bs / as_ + hk) / 2.0
        if asr > -100.0:
            bvn = (
                a
                * math.exp(asr)
                * (1.0 - c * (bs - as_) * (1.0 - d * bs / 5.0) / 3.0 + c * d * as_ * as_ / 5.0)
            )
        if hk > -100.0:
            b = math.sqrt(bs)
            bvn -= (
                math.exp(-hk / 2.0)
                * math.sqrt(_TWOPI)
                * _phi(-b / a)
                * b
                * (1.0 - c * bs * (1.0 - d * bs / 5.0) / 3.0)
            )
        a = a / 2.0
        for i in range(ng):
            xs = (a + a * glx[g, i]) ** 2
            rs = math.sqrt(1.0 - xs)
            asr2 = -(bs / xs + hk) / 2.0
            if asr2 > -100.0:
                sp = 1.0 + c * xs * (1.0 + d * xs)
                ep = math.exp(-hk * xs / (2.0 * (1.0 + rs) ** 2)) / rs
                bvn += a * glw[g, i] * math.exp(asr2) * (ep - sp)
        bvn = -bvn / _TWOPI
    if r > 0.0:
        bvn += _phi(-max(dh, dk))
    elif dh >= dk:
        bvn = -bvn
    else:
        if dh < 0.0:
            L = _phi(dk) - _phi(dh)
        else:
            L = _phi(-dh) - _phi(-dk)
        bvn = L - bvn
    bvn = min(1.0, max(0.0, bvn))
    return bvn - _phi(h) * _phi(k)


#: Below this |r| the covariance comes from the tetrachoric series (``_hermite_rows``).
R_SERIES = 0.3
#: Terms kept: |r|^n < 1e-16 by n = 31 at |r| = 0.3.
N_SERIES = 32


def _hermite_rows(s: FloatArray) -> FloatArray:
    """c_n(s) = phi(s) He_{n-1}(s) / sqrt((n-1)! n), n = 1..N_SERIES, shape (len(s), N_SERIES).

    Tetrachoric (Mehler) series: Phi2(h, k; r) - Phi(h) Phi(k) = sum_n r^n c_n(h) c_n(k)
    (Kendall & Stuart, Vol. 2, eq. 33.33; Mehler's formula integrated). Cramer's bound
    |He_m(x)| <= 1.087 sqrt(m!) exp(x^2/4) gives |c_n(h) c_n(k)| <= 0.19 / n, so at
    |r| < 0.3 the tail after 31 terms is below 1e-17 and every term is bounded: no
    cancellation. He is built by the normalised recurrence
    e_{m+1} = (x e_m - sqrt(m) e_{m-1}) / sqrt(m + 1), e_m = He_m / sqrt(m!).
    """
    s = np.asarray(s, dtype=np.float64)
    out = np.empty((s.size, N_SERIES))
    phi = np.exp(-0.5 * s * s) / math.sqrt(_TWOPI)
    e_prev = np.zeros_like(s)
    e = np.ones_like(s)
    for m in range(N_SERIES):  # column m holds n = m + 1, i.e. He_m
        out[:, m] = phi * e / math.sqrt(m + 1.0)
        e_next = (s * e - math.sqrt(m) * e_prev) / math.sqrt(m + 1.0)
        e_prev, e = e, e_next
    return out


@numba.njit(parallel=True, cache=True)
def _tile_cov_sum(
    s_i: FloatArray,
    s_j: FloatArray,
    sd_i: FloatArray,
    sd_j: FloatArray,
    cov: FloatArray,
    upper_only: bool,
    c_i: FloatArray,
    c_j: FloatArray,
    glx: FloatArray,
    glw: FloatArray,
) -> float:
    """sum_ij [Phi2(s_i, s_j; r_ij) - p_i p_j] over a tile (strict upper triangle if asked).

    On a diagonal tile (upper_only) row a has ni - 1 - a pairs; iteration a takes rows a
    and ni - 1 - a together so that the threads get equal work.
    """
    ni = s_i.size
    nj = s_j.size
    n_iter = (ni + 1) // 2 if upper_only else ni
    part = np.zeros(n_iter)
    for it in numba.prange(n_iter):
        acc = 0.0
        n_rep = 1
        if upper_only and ni - 1 - it != it:
            n_rep = 2
        for rep in range(n_rep):
            a = np.int64(it)
            if rep == 1:
                a = np.int64(ni - 1) - a
            j0 = a + 1 if upper_only else np.int64(0)
            sa = sd_i[a]
            for b in range(j0, nj):
                r = cov[a, b] / (sa * sd_j[b])
                if abs(r) < R_SERIES:
                    # Tetrachoric series (``_hermite_rows``); stops once |r|^n < 1e-16.
                    rn = r
                    for n in range(N_SERIES):
                        acc += rn * c_i[a, n] * c_j[b, n]
                        rn *= r
                        if abs(rn) < 1e-16:
                            break
                else:
                    acc += _bvn_cov(s_i[a], s_j[b], min(1.0, max(-1.0, r)), glx, glw)
        part[it] = acc
    return part.sum()


def bvn_cov(h: ArrayLike, k: ArrayLike, r: ArrayLike) -> FloatArray:
    """Phi2(h, k; r) - Phi(h) Phi(k), elementwise (the covariance of two failure indicators).

    Parameters
    ----------
    h, k, r : array_like, broadcastable; h, k finite, r in [-1, 1]

    Returns
    -------
    c : ndarray of the broadcast shape
    """
    h, k, r = np.broadcast_arrays(
        np.asarray(h, np.float64), np.asarray(k, np.float64), np.asarray(r, np.float64)
    )
    out = np.empty(h.shape)
    flat = out.reshape(-1)
    hf, kf, rf = h.reshape(-1), k.reshape(-1), np.clip(r.reshape(-1), -1.0, 1.0)
    for t in range(flat.size):
        flat[t] = _bvn_cov(hf[t], kf[t], rf[t], _GL_X, _GL_W)
    return out


def gp_variance_exact(
    mu: ArrayLike,
    sigma2: ArrayLike,
    cov_block: Callable[[IntArray, IntArray], FloatArray],
    gamma: float,
    tile: int = 2048,
    progress: Callable[[int, int], None] | None = None,
    *,
    h_tol: float = 1e-12,
) -> GPVariance:
    """Var(p_hat_GP) = (1/N^2) sum_ij [Phi2(s_i, s_j; r_ij) - p_i p_j] (paper appendix B.1).

    s = (gamma - mu) / sigma, r_ij = cov_n(x_i, x_j) / (sigma_i sigma_j); diagonal terms are
    p_i (1 - p_i). The double sum runs over square tiles of the units with
    h_i = p_i (1 - p_i) >= h_tol, the upper triangle only (the sum is symmetric), in numba on
    all cores. The pair term Phi2 - p_i p_j is computed directly, never as a difference: by
    the tetrachoric series for |r| < 0.3 (``_hermite_rows``; ~10-30 multiply-adds, the bulk
    of the pairs in a GP posterior) and by Genz's quadrature otherwise (``_bvn_cov``), both
    to ~1e-16 absolute. Memory is one tile of covariances plus (n_kept, 32) coefficients.

    Skipping is exact up to a returned bound: |cov(g_i, g_j)| <= sqrt(h_i h_j)
    (Cauchy-Schwarz), so the off-diagonal pairs with a skipped unit move Var by at most
    ((sum_all sqrt h)^2 - (sum_kept sqrt h)^2 - sum_skipped h) / N^2.

    Parameters
    ----------
    mu : array_like of shape (n_pool,)
        Posterior mean of theta0 at the pool.
    sigma2 : array_like of shape (n_pool,)
        Posterior variance of theta0 at the pool.
    cov_block : callable (rows, cols) -> ndarray of shape (len(rows), len(cols))
        Posterior covariance cov_n(theta0(x_rows), theta0(x_cols)), rows and cols being int
        arrays of pool indices, e.g. ``lambda r, c: gp.cov_theta0(X[r], X[c])``. Index
        arrays rather than ranges because the kept units are not contiguous.
    gamma : float
        Failure threshold.
    tile : int
        Tile side; memory is ~8 tile^2 bytes.
    progress : callable (tiles_done, n_tiles) -> None, optional
        Called after every tile.
    h_tol : float
        Units with p (1 - p) below this are left out of the pairs (their diagonal counts);
        the effect is bounded by ``GPVariance.skipped_bound``. 0 computes every pair.

    Returns
    -------
    GPVariance
    """
    mu = np.asarray(mu, dtype=np.float64)
    sigma2 = np.asarray(sigma2, dtype=np.float64)
    N = mu.size
    sd = np.sqrt(np.maximum(sigma2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(
            sd > 0, (gamma - mu) / np.where(sd > 0, sd, 1.0), np.where(mu <= gamma, np.inf, -np.inf)
        )
    h = ndtr(s) * ndtr(-s)  # p (1 - p) without the cancelling 1 - p
    # h = 0 (p exactly 0 or 1, e.g. sigma = 0) contributes exactly nothing off the diagonal.
    keep = np.flatnonzero((h >= h_tol) & (h > 0))
    diag = float(h.sum())
    sqrt_h = np.sqrt(h)
    all_sum = float(sqrt_h.sum())
    kept_sum = float(sqrt_h[keep].sum())
    skipped_h = diag - float(h[keep].sum())
    bound = max(all_sum**2 - kept_sum**2 - skipped_h, 0.0) / N**2
    c_all = _hermite_rows(s[keep])  # series coefficients of the kept units, in keep order
    tile = max(1, int(tile))
    starts = list(range(0, keep.size, tile))
    n_tiles = len(starts) * (len(starts) + 1) // 2
    off = 0.0
    done = 0
    for bi, i0 in enumerate(starts):
        rows = keep[i0 : i0 + tile]
        for j0 in starts[bi:]:
            cols = keep[j0 : j0 + tile]
            C = np.ascontiguousarray(cov_block(rows, cols), dtype=np.float64)
            if C.shape != (rows.size, cols.size):
                raise ValueError(
                    f"cov_block returned shape {C.shape}; expected {(rows.size, cols.size)}"
                )
            off += _tile_cov_sum(
                s[rows], s[cols], sd[rows], sd[cols], C, j0 == i0,
                c_all[i0 : i0 + tile], c_all[j0 : j0 + tile], _GL_X, _GL_W,
            )  # fmt: skip
            done += 1
            if progress is not None:
                progress(done, n_tiles)
    var = (diag + 2.0 * off) / N**2
    return GPVariance(var=var, skipped_bound=bound, h_mean=diag / N, n_kept=int(keep.size))
