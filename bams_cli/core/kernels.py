"""Matern-5/2 ARD kernel, vectorised, and the pieces of it the GP gradient needs.

    k(x, x') = s2 (1 + sqrt5 r + 5/3 r^2) exp(-sqrt5 r),
    r^2      = sum_j ((x_j - x'_j) / ell_j)^2

(GPML eq. 4.17 with nu = 5/2; Rasmussen & Williams 2006). Written with z = sqrt5 r as
s2 (1 + z + z^2 / 3) exp(-z), which needs one exp and no division.

Derivative used by the training gradient (``gp._MAPObjective``): with
D_j = ((x_j - x'_j) / ell_j)^2,

    dk / dlog ell_j = 5/3 s2 (1 + sqrt5 r) exp(-sqrt5 r) D_j

which is finite at r = 0 (it is 0 there), so no special case is needed.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.spatial.distance import cdist

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SQRT5 = math.sqrt(5.0)

#: Threads ``matern52_cross`` and ``matern52_cross_minus`` split their rows over; None:
#: every core. Pool workers set 1 (``parallel``): their siblings hold the other cores.
_THREADS: int | None = None
#: Below this many output entries one thread does it (a thread pool costs ~0.1 ms).
_THREADED_FROM = 1 << 18


def set_kernel_threads(n: int | None) -> None:
    """Threads the row kernels may use in this process (None: every core)."""
    global _THREADS
    _THREADS = n


@contextmanager
def kernel_threads(n: int | None) -> Iterator[None]:
    """``set_kernel_threads(n)`` for the block's time (as ``threadpool_limits`` for BLAS)."""
    before = _THREADS
    set_kernel_threads(n)
    try:
        yield
    finally:
        set_kernel_threads(before)


def _by_rows(kernel: Callable[..., None], na: int, nb: int, *args: object) -> None:
    """``kernel(lo, hi, *args)`` over contiguous row ranges [lo, hi) of na, on threads.

    The compiled kernels release the GIL (``nogil``), so plain Python threads run them side
    by side. Not numba's own threading layer: its OpenMP threads leave a process unable to
    fork workers that use them again (``select`` forks its cluster workers after scoring
    the pool); these threads are joined before the call returns.
    """
    threads = min(_THREADS or os.cpu_count() or 1, max(1, na))
    if threads == 1 or na * nb < _THREADED_FROM:
        kernel(0, na, *args)
        return
    cuts = np.linspace(0, na, threads + 1).astype(np.int64)
    with ThreadPoolExecutor(threads, thread_name_prefix="bams-kernel") as pool:
        spans = zip(cuts[:-1], cuts[1:], strict=True)
        for f in [pool.submit(kernel, int(lo), int(hi), *args) for lo, hi in spans]:
            f.result()


def scaled_sqdist(
    XA: FloatArray, XB: FloatArray, lengthscales: FloatArray, *, exact: bool = False
) -> FloatArray:
    """Squared distances after dividing every dimension by its lengthscale.

    Parameters
    ----------
    XA : ndarray of shape (na, d)
    XB : ndarray of shape (nb, d)
    lengthscales : ndarray of shape (d,)
    exact : bool
        False (default): |a|^2 + |b|^2 - 2 a.b with one BLAS matmul, clipped at 0. Its
        rounding error is ~1e-16 (|a|^2 + |b|^2), harmless for a kernel that is flat in
        r^2 at r = 0, provided the inputs are centred (the GP centres them). True: direct
        differences (``scipy.spatial.distance.cdist``), exactly 0 for identical rows;
        used for the small training matrix, whose diagonal must be exactly s2.

    Returns
    -------
    r2 : ndarray of shape (na, nb)
    """
    A = XA / lengthscales
    B = XB / lengthscales
    if exact:
        return cdist(A, B, "sqeuclidean")
    r2 = A @ B.T
    r2 *= -2.0
    r2 += np.einsum("ij,ij->i", A, A)[:, None]
    r2 += np.einsum("ij,ij->i", B, B)[None, :]
    np.maximum(r2, 0.0, out=r2)
    return r2


def matern52_from_sqdist(
    r2: FloatArray, outputscale: float, *, overwrite: bool = False
) -> FloatArray:
    """Matern-5/2 covariance from scaled squared distances.

    Parameters
    ----------
    r2 : ndarray of any shape
        Scaled squared distances (``scaled_sqdist``).
    outputscale : float
        Kernel variance s2.
    overwrite : bool
        Reuse ``r2``'s memory for an intermediate (it is destroyed). Scoring a million
        pool points relies on this to keep three, not four, (chunk, n) arrays alive.

    Returns
    -------
    k : ndarray, same shape as r2
    """
    z = np.sqrt(r2, out=r2 if overwrite else None)
    z *= SQRT5
    e = np.negative(z)
    np.exp(e, out=e)
    # Horner: 1 + z + z^2/3 = 1 + z (1 + z/3)
    k = z / 3.0
    k += 1.0
    k *= z
    k += 1.0
    k *= e
    k *= outputscale
    return k


def matern52(
    XA: FloatArray,
    XB: FloatArray,
    lengthscales: FloatArray,
    outputscale: float,
    *,
    exact: bool = False,
) -> FloatArray:
    """Matern-5/2 ARD covariance matrix k(XA, XB).

    Parameters
    ----------
    XA : ndarray of shape (na, d)
    XB : ndarray of shape (nb, d)
    lengthscales : ndarray of shape (d,)
    outputscale : float
        Kernel variance s2 (k(x, x) = s2).
    exact : bool
        See ``scaled_sqdist``.

    Returns
    -------
    K : ndarray of shape (na, nb)
    """
    r2 = scaled_sqdist(XA, XB, lengthscales, exact=exact)
    return matern52_from_sqdist(r2, outputscale, overwrite=True)


def matern52_and_grad_factor(z2: FloatArray, outputscale: float) -> tuple[FloatArray, FloatArray]:
    """Kernel values and the factor G with dk/dlog ell_j = G * D_j, from z^2 = 5 r^2.

    Takes z^2 rather than r^2 so the caller folds the 5 into its lengthscale weights and
    the z^2 / 3 term reuses the input: the training objective calls this at every
    L-BFGS-B evaluation, where each pass over the (n, n) arrays counts.

    Parameters
    ----------
    z2 : ndarray of shape (n, n)
        5 r^2, r the scaled distance. Overwritten (it becomes K).
    outputscale : float

    Returns
    -------
    K : ndarray of shape (n, n)
        s2 (1 + z + z^2/3) exp(-z), z = sqrt5 r.
    G : ndarray of shape (n, n)
        5/3 s2 (1 + z) exp(-z) (module docstring).
    """
    z = np.sqrt(z2)
    e = np.negative(z)
    np.exp(e, out=e)
    e *= outputscale
    z += 1.0
    G = np.multiply(z, e, out=z)  # s2 (1 + z) e^-z
    K = np.multiply(z2, 1.0 / 3.0, out=z2)
    K *= e
    K += G  # s2 e^-z (1 + z + z^2 / 3)
    G *= 5.0 / 3.0
    return K, G


def matern52_cross_minus(
    XA: FloatArray,
    XB: FloatArray,
    group: IntArray,
    lengthscales: FloatArray,
    outputscale: float,
    P: FloatArray,
) -> FloatArray:
    """k(XA, XB[group]) - P, computed in place in P, each distinct point of XB once.

    The cross-covariance the selection loop builds is rows x candidates, and a candidate
    point usually appears once per fidelity level: ``group`` maps every column of P to its
    point in XB, so the kernel is evaluated on XB's points only. One compiled pass per row,
    direct differences (as ``scaled_sqdist(..., exact=True)``), one exp per entry: the numpy
    path makes ten passes over rows x columns temporaries, which is memory-bound at the
    selection's sizes (a 7,500 x 15,000 block is 900 MB per temporary).

    Parameters
    ----------
    XA : ndarray of shape (na, d)
    XB : ndarray of shape (nb, d)
    group : int ndarray of shape (m,)
        Values in [0, nb): column j of P belongs to point XB[group[j]].
    lengthscales : ndarray of shape (d,)
    outputscale : float
    P : ndarray of shape (na, m), C-contiguous float64
        Overwritten with the result.

    Returns
    -------
    P : the same array, k(XA[i], XB[group[j]]) - P[i, j]
    """
    A = np.ascontiguousarray(XA / lengthscales, dtype=np.float64)
    BT = np.ascontiguousarray((XB / lengthscales).T, dtype=np.float64)
    group = np.ascontiguousarray(group, dtype=np.int64)
    if P.shape != (A.shape[0], group.shape[0]) or not P.flags.c_contiguous:
        raise ValueError(f"P must be C-contiguous of shape {(A.shape[0], group.shape[0])}")
    if group.size and not (0 <= group.min() and group.max() < BT.shape[1]):
        raise ValueError("group must index the rows of XB")
    _by_rows(_matern52_cross_minus, A.shape[0], P.shape[1], A, BT, group, float(outputscale), P)
    return P


def matern52_cross(
    XA: FloatArray, XB: FloatArray, lengthscales: FloatArray, outputscale: float
) -> FloatArray:
    """Matern-5/2 ARD covariance k(XA, XB), one compiled pass over the output.

    The same covariance as ``matern52(..., exact=True)`` (direct differences, so exactly
    s2 on identical rows), computed row by row with one exp per entry instead of numpy's
    ten passes over (na, nb) temporaries, rows split over threads (``_by_rows``).
    ``MFGP.score`` builds the pool x observations block with it: 0.18 CPU s for
    3,355 x 5,000 entries where numpy took 0.83, about a quarter of all scoring's CPU time
    at 5,000 observations, and nearly all of a bounded fit's first pass (a million
    segments x 12,000 observations).

    Parameters
    ----------
    XA : ndarray of shape (na, d)
    XB : ndarray of shape (nb, d)
    lengthscales : ndarray of shape (d,)
    outputscale : float

    Returns
    -------
    K : ndarray of shape (na, nb), C-contiguous
    """
    A = np.ascontiguousarray(XA / lengthscales, dtype=np.float64)
    BT = np.ascontiguousarray((XB / lengthscales).T, dtype=np.float64)
    K = np.empty((A.shape[0], BT.shape[1]))
    _by_rows(_matern52_cross, A.shape[0], BT.shape[1], A, BT, float(outputscale), K)
    return K


@njit(cache=True, error_model="numpy")
def _matern52_row(A, i, BT, s2, out):  # pragma: no cover
    """out[j] = s2 k52(|A[i] - BT[:, j]|) for every j (lengthscales already divided out)."""
    d = A.shape[1]
    nb = BT.shape[1]
    for j in range(nb):
        out[j] = 0.0
    for k in range(d):
        aik = A[i, k]
        bk = BT[k]
        for j in range(nb):
            diff = aik - bk[j]
            out[j] += diff * diff
    for j in range(nb):
        z = SQRT5 * math.sqrt(out[j])
        out[j] = s2 * (1.0 + z * (1.0 + z / 3.0)) * math.exp(-z)


@njit(cache=True, error_model="numpy", nogil=True)
def _matern52_cross(lo, hi, A, BT, s2, K):  # pragma: no cover
    for i in range(lo, hi):
        _matern52_row(A, i, BT, s2, K[i])


@njit(cache=True, error_model="numpy", nogil=True)
def _matern52_cross_minus(lo, hi, A, BT, group, s2, P):  # pragma: no cover
    krow = np.empty(BT.shape[1])
    for i in range(lo, hi):
        _matern52_row(A, i, BT, s2, krow)
        row = P[i]
        for j in range(group.shape[0]):
            row[j] = krow[group[j]] - row[j]


def matern52_aug_lower(
    X: FloatArray,
    levels: IntArray,
    lengthscales: FloatArray,
    outputscales: FloatArray,
    K: FloatArray,
) -> FloatArray:
    """Lower triangle of the multifidelity training covariance, written into K in place.

    K[i, j] = k0(x_i, x_j) + [l_i == l_j >= 1] k_{l_i}(x_i, x_j) for i >= j, each a
    Matern-5/2 ARD kernel with direct differences (as ``matern52(..., exact=True)``:
    exactly s0 + s_l on the diagonal). The strict upper triangle is not touched. No
    temporaries: the numpy path held three (n, n) arrays at once, which set the memory
    ceiling of exact conditioning. Serial: O(n^2 d) against the factorisation's
    O(n^3 / 3).

    Parameters
    ----------
    X : ndarray of shape (n, d)
    levels : int ndarray of shape (n,)
    lengthscales : ndarray of shape (n_levels, d)
        Row 0 for k0, row l for the discrepancy k_l.
    outputscales : ndarray of shape (n_levels,)
    K : ndarray of shape (n, n), Fortran-contiguous float64
        Overwritten in its lower triangle (with the diagonal).

    Returns
    -------
    K : the same array
    """
    n = X.shape[0]
    if K.shape != (n, n) or not K.flags.f_contiguous or K.dtype != np.float64:
        raise ValueError(f"K must be a Fortran-contiguous float64 array of shape {(n, n)}")
    ell = np.asarray(lengthscales, dtype=np.float64)
    # Scaled inputs per level, (n_levels, n, d): S[l, i] = x_i / ell_l.
    S = np.ascontiguousarray(np.stack([X / e for e in ell]), dtype=np.float64)
    _matern52_aug_lower(
        S,
        np.ascontiguousarray(levels, dtype=np.int64),
        np.ascontiguousarray(outputscales, dtype=np.float64),
        K,
    )
    return K


@njit(cache=True, error_model="numpy")
def _matern52_aug_lower(S, levels, s, K):  # pragma: no cover
    for j in range(S.shape[1]):
        _aug_column(S, levels, s, K, j)


@njit(cache=True, error_model="numpy")
def _aug_column(S, levels, s, K, j):  # pragma: no cover
    n, d = S.shape[1], S.shape[2]
    lj = levels[j]
    for i in range(j, n):
        r2 = 0.0
        for k in range(d):
            diff = S[0, i, k] - S[0, j, k]
            r2 += diff * diff
        z = SQRT5 * math.sqrt(r2)
        v = s[0] * (1.0 + z * (1.0 + z / 3.0)) * math.exp(-z)
        if lj >= 1 and levels[i] == lj:
            r2 = 0.0
            for k in range(d):
                diff = S[lj, i, k] - S[lj, j, k]
                r2 += diff * diff
            z = SQRT5 * math.sqrt(r2)
            v += s[lj] * (1.0 + z * (1.0 + z / 3.0)) * math.exp(-z)
        K[i, j] = v
