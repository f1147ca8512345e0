"""Numerics shared by the GP modules: the error type, data checks, standardisation and
the jittered Cholesky factorisation."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor

from bams_cli.core.hyperparameter_values import MAX_SCALE

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

LOG_2PI = math.log(2.0 * math.pi)
#: Cholesky jitter ladder, in units of the mean diagonal of K.
JITTERS = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)


class GPFitError(ValueError):
    """The GP cannot be built from these observations or hyperparameters."""


#: Smallest non-zero sd accepted: below it the natural-unit variances (sd^2 times the
#: standardised ones) underflow to 0 and the model has no scale at all.
MIN_SCALE = 1e-150


def standardise(y: FloatArray) -> tuple[float, float]:
    """(mean, std) used to standardise y; std 1 when y is constant or n = 1.

    Computed on y / max|y|, so values near the float limits do not overflow the sum.
    Constant y is legitimate (the caller records it: the model is then flat); a spread
    beyond ``MAX_SCALE``, or above 0 but below ``MIN_SCALE``, is an error, since no
    variance in natural units could hold it.

    Raises
    ------
    GPFitError
        y has non-finite values, or its sd exceeds ``MAX_SCALE`` or is below ``MIN_SCALE``
        (and not 0).
    """
    top = float(np.max(np.abs(y))) if y.size else 0.0
    if not math.isfinite(top):
        raise GPFitError("the observed values include inf or NaN; drop or repair those rows")
    if top == 0.0:
        return 0.0, 1.0
    u = y / top
    ybar = top * float(np.mean(u))
    ystd = top * float(np.std(u))
    if ystd > MAX_SCALE:
        raise GPFitError(
            f"the observed values spread over {ystd:.3g} (sd): too large for a GP in "
            f"float64 (limit {MAX_SCALE:g}); rescale the metric, e.g. report it in "
            "thousands, or check the results for a wrong value"
        )
    if 0.0 < ystd < MIN_SCALE:
        raise GPFitError(
            f"the observed values spread over {ystd:.3g} (sd): too small for a GP in "
            f"float64 (limit {MIN_SCALE:g}); rescale the metric, e.g. report it in "
            "millionths, or check the results for a wrong value"
        )
    if not ystd > 0.0:
        ystd = 1.0
    return ybar, ystd


def input_ranges(X: FloatArray) -> FloatArray:
    """Per-dimension range of the training inputs, 1 where it is 0 (one point, constant)."""
    r = np.ptp(X, axis=0)
    return np.where(r > 0.0, r, 1.0)


def cholesky(K: FloatArray) -> tuple[FloatArray, float]:
    """Lower Cholesky factor of K, adding escalating jitter to the diagonal if needed.

    Jitter is tried at 0, then 1e-10 .. 1e-4 times the mean diagonal: enough to rescue a
    positive semi-definite K made singular by duplicated noise-free points, too little to
    move a posterior noticeably. K is not modified.

    Parameters
    ----------
    K : ndarray of shape (n, n)

    Returns
    -------
    L : ndarray of shape (n, n)
        K + jitter I = L L^T in the lower triangle; the strict upper triangle holds
        leftovers (LAPACK ignores it; copying it away cost as much as the factorisation).
    jitter : float
        Absolute jitter added (0.0 if none was needed).

    Raises
    ------
    GPFitError
        K has non-finite entries, or is not positive definite even with the largest jitter.
    """
    n = K.shape[0]
    if not np.all(np.isfinite(K)):
        raise GPFitError(
            f"the {n}x{n} training covariance has non-finite entries; the inputs are too "
            "large for the lengthscales or the hyperparameters overflow: rescale X (e.g. "
            "standardise the embedding) or pass smaller outputscales"
        )
    scale = float(np.mean(np.diag(K))) if n else 1.0
    for rel in JITTERS:
        jitter = rel * scale
        A = K if jitter == 0.0 else K + jitter * np.eye(n)
        try:
            L, _ = cho_factor(A, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
        return L, jitter
    raise GPFitError(
        f"Cholesky factorisation of the {n}x{n} training covariance failed even with jitter "
        f"{JITTERS[-1]:g} x its mean diagonal ({scale:.3g}): it is numerically indefinite, "
        "which Matern covariances only become at extreme hyperparameters (lengthscales "
        "orders of magnitude beyond the input range with zero noise). Refit instead of "
        "passing fixed hyperparameters, or give every level a positive noise variance"
    )


def cholesky_inplace(K: FloatArray, rebuild: Callable[[], None]) -> tuple[FloatArray, float]:
    """``cholesky`` without a copy: K is factorised where it lies.

    The same jitter ladder and errors as ``cholesky``; a failed attempt has overwritten K,
    so ``rebuild`` refills it (the kernel costs O(n^2 d), the factorisation O(n^3)) before
    the next rung's jitter goes on the diagonal. Peak memory is K itself: the exact
    conditioning budget (``fit.BYTES_PER_ENTRY``) rests on this.

    Parameters
    ----------
    K : ndarray of shape (n, n), Fortran-contiguous float64
        Lower triangle (with the diagonal) holds the covariance; overwritten by the factor.
    rebuild : callable
        Writes the covariance into K's lower triangle again.

    Returns
    -------
    L : K itself, its lower triangle the factor of K + jitter I
    jitter : float
    """
    n = K.shape[0]
    step = max(1, (1 << 22) // max(n, 1))  # bounded temporaries for the finiteness test
    for j in range(0, n, step):
        if not np.all(np.isfinite(K[j:, j : j + step])):
            raise GPFitError(
                f"the {n}x{n} training covariance has non-finite entries; the inputs are too "
                "large for the lengthscales or the hyperparameters overflow: rescale X (e.g. "
                "standardise the embedding) or pass smaller outputscales"
            )
    diag = np.diag_indices(n)
    scale = float(np.mean(K[diag])) if n else 1.0
    for attempt, rel in enumerate(JITTERS):
        jitter = rel * scale
        if attempt > 0:
            rebuild()
            K[diag] += jitter
        try:
            L, _ = cho_factor(K, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
        if not np.shares_memory(L, K):  # pragma: no cover - scipy copies only non-F input
            K[...] = L
        return K, jitter
    raise GPFitError(
        f"Cholesky factorisation of the {n}x{n} training covariance failed even with jitter "
        f"{JITTERS[-1]:g} x its mean diagonal ({scale:.3g}): it is numerically indefinite, "
        "which Matern covariances only become at extreme hyperparameters (lengthscales "
        "orders of magnitude beyond the input range with zero noise). Refit instead of "
        "passing fixed hyperparameters, or give every level a positive noise variance"
    )


def check_data(
    X: Any, levels: Any, y: Any, n_levels: int
) -> tuple[FloatArray, IntArray, FloatArray]:
    """Validate and convert training data; GPFitError naming the first bad row."""
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if X.ndim != 2:
        raise GPFitError(f"X must have shape (n, d), got shape {X.shape}")
    n = X.shape[0]
    levels = check_levels(levels, n_levels, n, "levels")
    if y.shape != (n,):
        raise GPFitError(f"y must have shape ({n},) to match X, got shape {y.shape}")
    if n == 0:
        raise GPFitError("no observations: the GP needs at least one (x, level, y) row")
    for name, arr in (("X", X), ("y", y)):
        bad = ~np.isfinite(arr)
        if bad.any():
            row = int(np.flatnonzero(bad.reshape(n, -1).any(axis=1))[0])
            raise GPFitError(
                f"{name} has {int(bad.sum())} non-finite value(s), first in row {row}; "
                "drop or repair those observations before fitting"
            )
    return X, levels, y


def check_levels(levels: Any, n_levels: int, n: int, name: str) -> IntArray:
    """Levels as int64 of shape (n,), each in [0, n_levels)."""
    lv = np.asarray(levels)
    if lv.shape != (n,):
        raise GPFitError(f"{name} must have shape ({n},), got shape {lv.shape}")
    if lv.size and not np.issubdtype(lv.dtype, np.integer):
        if not np.all(np.isfinite(lv)) or np.any(lv != np.round(lv)):
            raise GPFitError(f"{name} must be integers in [0, {n_levels}), got {lv.dtype}")
    lv = lv.astype(np.int64)
    if lv.size and (lv.min() < 0 or lv.max() >= n_levels):
        raise GPFitError(
            f"{name} must lie in [0, {n_levels}) for n_levels = {n_levels}, got values in "
            f"[{lv.min()}, {lv.max()}]; pass the study's number of levels as n_levels"
        )
    return lv
