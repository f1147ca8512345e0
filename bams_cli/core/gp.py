"""Multifidelity Gaussian process: MAP training and the posterior BAMS needs.

Model (paper section 3, "Multifidelity sampling"; DESIGN.md "The math"). Levels
l = 0..L, level 0 the high-fidelity simulator. An observation of segment x at level l is

    y = m + theta0(x) + alpha_l(x) + eps_l,   alpha_0 = 0,   eps_l ~ N(0, tau_l^2),

with a constant mean m, theta0 ~ GP(0, k0) and independent alpha_l ~ GP(0, k_l), each a
Matern-5/2 ARD kernel with its own lengthscales and output scale (``kernels.py``). So

    k_aug((x, a), (x', b)) = k0(x, x') + [a == b >= 1] k_a(x, x')      # paper, sec. 3

and the training covariance is K = k_aug(Y_n, Y_n) + diag(tau_{l_j}^2): the noise sits on
the true diagonal only. Two observations of the same (x, l) are distinct observations
whose noises are independent, so repeats share k_aug but not noise.

Everything in ``MFGP`` is computed in natural units from natural-unit hyperparameters.
Training works on standardised outputs (y - mean(y)) / std(y), where the priors and bounds
below make sense for any data scale, and converts the result back; the fitted
hyperparameters are therefore equivariant to rescaling y.

Training (``fit_mfgp``): maximum a posteriori over the log of every positive parameter,
scipy L-BFGS-B with analytic gradients (one Cholesky and one potri inverse per
evaluation), several seeded restarts, each screened for a few iterations before the best
are run to convergence, BLAS pinned to one thread. The constant mean is
profiled out in closed form (generalised least squares, m_hat = 1'K^-1 y / 1'K^-1 1) at
every evaluation rather than optimised: one parameter fewer, and by the envelope theorem
the gradient of the profiled objective is the usual one evaluated at m_hat. The mean is
then a plug-in estimate (its own uncertainty is not propagated into predictions, as for
every other hyperparameter).

Priors (all LogNormal densities on the positive parameter itself, the GPyTorch/BoTorch
convention, in standardised units; a LogNormal(loc, scale) then has its MAP mode at
exp(loc - scale^2), and in log space it is a Gaussian around that mode with sd ``scale``):

- lengthscales, theta0 and every discrepancy kernel: LogNormal(sqrt2 + log(d)/2, sqrt3) on
  the lengthscale in unit-cube units (each input dimension divided by its range over the
  training inputs, as BoTorch's Normalize transform does), i.e. BoTorch's dimension-scaled
  default (Hvarfner et al. 2024). Why: with tens of observations in d = 12 maximum
  likelihood happily picks short lengthscales that interpolate and then knows nothing
  between points; scaling the prior with sqrt(d) keeps the expected correlation between
  two random points roughly constant as d grows. Mode 0.20 sqrt(d) x range.
- outputscale0: mode 1 (the standardised data variance), log-sd 1.5: weak.
- discrepancy outputscales: mode 0.01, log-sd 1.0: a cheap simulator is a priori close to
  theta0 (a discrepancy sd ~10% of the data's), which is why it is worth running; the data
  overrule this when the levels disagree. Why this tight: with a handful of level-0 points
  among a hundred cheap ones, theta0 and the discrepancy are barely identified, and the
  former prior (mode 0.1, log-sd 1.5) let the MAP hand whole input directions of f to the
  discrepancy (theta0 lengthscale 15-60 along x1 or x0 on toy2d, discrepancy scale ~1),
  leaving theta0 confidently wrong where the cheap data said otherwise
  (docs/reproduction/README.md, "What moved the numbers").
- level-0 noise tau_0^2: mode 3e-4, log-sd 1.0. Never a fixed tiny jitter (a GP that is
  sure of itself at the kinks of f produced p_n ~ 1e-28 for true failures and an infinite
  importance-sampling variance) and never free (free maximum likelihood explained all the
  level-0 data as noise on some seeds; with log-sd 1.5 the MAP still did so on one toy2d
  seed in ten, tau_0^2 = 0.07 of the data variance, together with the discrepancy above).
  Explaining the data as noise (tau_0^2 ~ 0.5) costs ~27 nats of prior; a true 1e-2 costs
  ~6, which data that can identify the noise (repeats, points closer than a lengthscale)
  readily pay (``test_map_recovers_hyperparameters_of_data_drawn_from_the_prior`` recovers
  a level-0 noise of 2% of the variance). Where the data cannot tell noise from roughness
  (100 scattered points in 4-d, noise 1e-2 of the variance: the likelihood is flat within
  0.3 nats over 1e-4..1e-2), the prior decides and the fit returns ~5e-4.
- noise at levels >= 1: mode 3e-3, log-sd 2: cheap simulators are often noisy; weak.

Numerics: Cholesky with escalating relative jitter (``_cholesky``); predictions reuse the
factor L and alpha = K^-1 (y - m) computed once at construction (GPML Alg. 2.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.linalg.lapack import dpotri
from scipy.optimize import OptimizeResult, minimize
from scipy.special import ndtr
from threadpoolctl import threadpool_limits

from bams_cli.core.kernels import matern52, matern52_and_grad_factor

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["GPFitError", "Hyperparameters", "MFGP", "fit_mfgp"]

_LOG_2PI = math.log(2.0 * math.pi)

# Prior modes and log-space sds in standardised units (module docstring says why).
_OUTPUTSCALE0_MODE, _OUTPUTSCALE0_SCALE = 1.0, 1.5
_DISCREPANCY_MODE, _DISCREPANCY_SCALE = 0.01, 1.0
_NOISE0_MODE, _NOISE0_SCALE = 3e-4, 1.0
_NOISE_MODE, _NOISE_SCALE = 3e-3, 2.0
_LENGTHSCALE_SCALE = math.sqrt(3.0)

# Box bounds on the standardised parameters. Wide: the priors do the regularising; the
# bounds only keep L-BFGS-B away from overflow and from singular K.
_OUTPUTSCALE0_BOUNDS = (1e-4, 1e4)
_DISCREPANCY_BOUNDS = (1e-6, 1e4)
_LENGTHSCALE_BOUNDS = (5e-3, 1e3)  # in units of the training range of each dimension
_NOISE_BOUNDS = (1e-9, 1e1)

_SCREEN_ITER = 10  # L-BFGS-B iterations every restart gets
_N_POLISH = 2  # restarts continued to convergence
_MAXITER = 300  # cap on those; converged runs stop well before
_JITTERS = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)  # x mean diagonal of K
_MAX_DIFF_ELEMENTS = 30_000_000  # cache (n, n, d) squared differences below this size
_CHUNK_ELEMENTS = 1 << 24  # score(): at most this many (chunk x n_obs) kernel entries


class GPFitError(ValueError):
    """The GP cannot be built from these observations or hyperparameters."""


# --------------------------------------------------------------------------- parameters


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
    """

    mean: float
    outputscale0: float
    lengthscales0: FloatArray
    outputscales: FloatArray
    lengthscales: FloatArray
    noise: FloatArray

    def __post_init__(self) -> None:
        ell0 = np.array(self.lengthscales0, dtype=np.float64).reshape(-1)
        d = ell0.size
        s = np.array(self.outputscales, dtype=np.float64).reshape(-1)
        ell = np.array(self.lengthscales, dtype=np.float64)
        if ell.size != s.size * d:
            raise ValueError(
                f"Hyperparameters: lengthscales has shape {ell.shape}, expected (L, d) = "
                f"({s.size}, {d}) from outputscales and lengthscales0"
            )
        ell = ell.reshape(s.size, d)
        noise = np.array(self.noise, dtype=np.float64).reshape(-1)
        if noise.size != s.size + 1:
            raise ValueError(
                f"Hyperparameters: noise has {noise.size} entries but outputscales has "
                f"{s.size}; expected one noise variance per level (L + 1 = {s.size + 1})"
            )
        positive = {
            "outputscale0": np.array([self.outputscale0], dtype=np.float64),
            "lengthscales0": ell0,
            "outputscales": s,
            "lengthscales": ell,
        }
        for name, value in positive.items():
            if not np.all(np.isfinite(value) & (value > 0)):
                raise ValueError(f"Hyperparameters: {name} must be finite and > 0, got {value}")
        # Noise 0 is allowed for fixed hyperparameters (tests, noise-free what-ifs); the
        # fit never produces it.
        if not np.all(np.isfinite(noise) & (noise >= 0)):
            raise ValueError(f"Hyperparameters: noise must be finite and >= 0, got {noise}")
        if not math.isfinite(float(self.mean)):
            raise ValueError(f"Hyperparameters: mean must be finite, got {self.mean}")
        # Frozen means frozen: store float64 copies and make them read-only.
        object.__setattr__(self, "mean", float(self.mean))
        object.__setattr__(self, "outputscale0", float(self.outputscale0))
        for name, arr in [
            ("lengthscales0", ell0),
            ("outputscales", s),
            ("lengthscales", ell),
            ("noise", noise),
        ]:
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

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
                for f in ("lengthscales0", "outputscales", "lengthscales", "noise")
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
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Hyperparameters:
        """Inverse of ``to_dict``.

        Parameters
        ----------
        d : dict
            As written by ``to_dict``. ``lengthscales`` may be ``[]`` when L = 0.
        """
        ell0 = np.asarray(d["lengthscales0"], dtype=np.float64)
        s = np.asarray(d["outputscales"], dtype=np.float64)
        ell = np.asarray(d["lengthscales"], dtype=np.float64).reshape(s.size, ell0.size)
        return cls(
            mean=float(d["mean"]),
            outputscale0=float(d["outputscale0"]),
            lengthscales0=ell0,
            outputscales=s,
            lengthscales=ell,
            noise=np.asarray(d["noise"], dtype=np.float64),
        )


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
    theta: FloatArray, mean: float, d: int, n_levels: int, ybar: float, ystd: float
) -> Hyperparameters:
    """Natural-unit Hyperparameters from standardised theta and standardised mean."""
    s, ell, noise = _unpack(theta, d, n_levels)
    v = ystd**2
    return Hyperparameters(
        mean=ybar + ystd * mean,
        outputscale0=float(s[0] * v),
        lengthscales0=ell[0],
        outputscales=s[1:] * v,
        lengthscales=ell[1:],
        noise=noise * v,
    )


def _standardise(y: FloatArray) -> tuple[float, float]:
    """(mean, std) used to standardise y; std 1 when y is constant or n = 1."""
    ybar = float(np.mean(y))
    ystd = float(np.std(y))
    if not (math.isfinite(ystd) and ystd > 0.0):
        ystd = 1.0
    return ybar, ystd


def _input_ranges(X: FloatArray) -> FloatArray:
    """Per-dimension range of the training inputs, 1 where it is 0 (one point, constant)."""
    r = np.ptp(X, axis=0)
    return np.where(r > 0.0, r, 1.0)


@dataclass(frozen=True)
class _Priors:
    """Independent LogNormal(loc, scale) priors on exp(theta), and box bounds on theta.

    All arrays have the layout of ``_pack``. Standardised units.
    """

    loc: FloatArray
    scale: FloatArray
    lower: FloatArray
    upper: FloatArray

    @classmethod
    def for_data(cls, X: FloatArray, n_levels: int) -> _Priors:
        """Priors for training inputs X of shape (n, d) and ``n_levels`` levels."""
        d = X.shape[1]
        m = n_levels
        log_range = np.log(_input_ranges(X))

        def from_mode(mode: float, scale: float) -> float:
            # LogNormal(loc, scale) has its mode at exp(loc - scale^2).
            return math.log(mode) + scale**2

        # BoTorch's dimension-scaled lengthscale prior, on unit-cube lengthscales; moving
        # to natural units shifts loc by log(range) per dimension.
        ell_loc = math.sqrt(2.0) + 0.5 * math.log(d) + log_range
        loc = np.concatenate(
            [
                [from_mode(_OUTPUTSCALE0_MODE, _OUTPUTSCALE0_SCALE)],
                np.full(m - 1, from_mode(_DISCREPANCY_MODE, _DISCREPANCY_SCALE)),
                np.tile(ell_loc, m),
                [from_mode(_NOISE0_MODE, _NOISE0_SCALE)],
                np.full(m - 1, from_mode(_NOISE_MODE, _NOISE_SCALE)),
            ]
        )
        scale = np.concatenate(
            [
                [_OUTPUTSCALE0_SCALE],
                np.full(m - 1, _DISCREPANCY_SCALE),
                np.full(m * d, _LENGTHSCALE_SCALE),
                [_NOISE0_SCALE],
                np.full(m - 1, _NOISE_SCALE),
            ]
        )
        lower = np.log(
            np.concatenate(
                [
                    [_OUTPUTSCALE0_BOUNDS[0]],
                    np.full(m - 1, _DISCREPANCY_BOUNDS[0]),
                    np.tile(_LENGTHSCALE_BOUNDS[0] * np.exp(log_range), m),
                    np.full(m, _NOISE_BOUNDS[0]),
                ]
            )
        )
        upper = np.log(
            np.concatenate(
                [
                    [_OUTPUTSCALE0_BOUNDS[1]],
                    np.full(m - 1, _DISCREPANCY_BOUNDS[1]),
                    np.tile(_LENGTHSCALE_BOUNDS[1] * np.exp(log_range), m),
                    np.full(m, _NOISE_BOUNDS[1]),
                ]
            )
        )
        return cls(loc=loc, scale=scale, lower=lower, upper=upper)

    @property
    def mode(self) -> FloatArray:
        """theta at the prior mode, clipped to the bounds."""
        return np.clip(self.loc - self.scale**2, self.lower, self.upper)

    def sample_start(self, rng: np.random.Generator) -> FloatArray:
        """A restart point: theta ~ N(mode, scale^2), clipped to the bounds.

        Centred on the mode rather than the median: the lengthscale prior's median
        (4.1 sqrt(d) x range) is far beyond where the MAP usually lands.
        """
        return np.clip(rng.normal(self.loc - self.scale**2, self.scale), self.lower, self.upper)

    def log_prior(self, theta: FloatArray) -> tuple[float, FloatArray]:
        """Sum of LogNormal log densities of exp(theta) and its gradient wrt theta.

        log p(v) = -log v - log(scale sqrt(2 pi)) - (log v - loc)^2 / (2 scale^2), v = exp(theta).
        """
        u = (theta - self.loc) / self.scale
        value = float(np.sum(-theta - np.log(self.scale) - 0.5 * _LOG_2PI - 0.5 * u * u))
        grad = -1.0 - u / self.scale
        return value, grad


# ------------------------------------------------------------------------------ numerics


def _cholesky(K: FloatArray) -> tuple[FloatArray, float]:
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
    for rel in _JITTERS:
        jitter = rel * scale
        A = K if jitter == 0.0 else K + jitter * np.eye(n)
        try:
            L, _ = cho_factor(A, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            continue
        return L, jitter
    raise GPFitError(
        f"Cholesky factorisation of the {n}x{n} training covariance failed even with jitter "
        f"{_JITTERS[-1]:g} x its mean diagonal ({scale:.3g}): it is numerically indefinite, "
        "which Matern covariances only become at extreme hyperparameters (lengthscales "
        "orders of magnitude beyond the input range with zero noise). Refit instead of "
        "passing fixed hyperparameters, or give every level a positive noise variance"
    )


def _check_data(
    X: Any, levels: Any, y: Any, n_levels: int
) -> tuple[FloatArray, IntArray, FloatArray]:
    """Validate and convert training data; GPFitError naming the first bad row."""
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if X.ndim != 2:
        raise GPFitError(f"X must have shape (n, d), got shape {X.shape}")
    n = X.shape[0]
    levels = _check_levels(levels, n_levels, n, "levels")
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


def _check_levels(levels: Any, n_levels: int, n: int, name: str) -> IntArray:
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

    f(theta) = -log N(y | m_hat 1, K) - log p(theta), with m_hat the GLS mean. Gradient
    (GPML eq. 5.9, with K^-1 from the Cholesky factor):
    d(-log N)/dtheta_i = 1/2 tr((K^-1 - alpha alpha^T) dK/dtheta_i), alpha = K^-1 (y - m_hat).
    Each trace is an elementwise sum (both matrices symmetric), and all lengthscale traces
    of one kernel come from one contraction with the cached squared differences
    (``kernels`` module docstring for dk/dlog ell_j), so one evaluation costs one Cholesky,
    one inverse and O(n^2 d).

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
        self._ones_y = np.column_stack([np.ones(self.n), y])
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

    def gls_mean(self, L: FloatArray) -> tuple[float, FloatArray]:
        """GLS mean m_hat = 1'K^-1 y / 1'K^-1 1 and alpha = K^-1 (y - m_hat)."""
        Kinv_1, Kinv_y = cho_solve((L, True), self._ones_y, check_finite=False).T
        m = float(Kinv_1 @ self.y / Kinv_1.sum())
        return m, Kinv_y - m * Kinv_1

    def __call__(self, theta: FloatArray) -> tuple[float, FloatArray]:
        """f(theta) and df/dtheta, shape (len(theta),)."""
        s, ell, noise = _unpack(theta, self.d, self.n_levels)
        K, parts, _ = self.covariance(theta)
        try:
            L, _ = _cholesky(K)
        except GPFitError:
            # Only reachable through overflow at extreme bounds; L-BFGS-B backtracks.
            return math.inf, np.zeros_like(theta)
        m, alpha = self.gls_mean(L)
        r = self.y - m
        nll = 0.5 * float(r @ alpha) + float(np.sum(np.log(np.diag(L)))) + 0.5 * self.n * _LOG_2PI
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

        m_ = self.n_levels
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
        grad[m_ + m_ * self.d :] = (
            0.5 * noise * np.bincount(self.levels, weights=diag_Kinv - alpha**2, minlength=m_)
        )

        lp, lp_grad = self.priors.log_prior(theta)
        return nll - lp, grad - lp_grad


# ------------------------------------------------------------------------------- fitting


def _minimize(
    objective: _MAPObjective, theta: FloatArray, bounds: list, maxiter: int
) -> OptimizeResult:
    return minimize(
        objective, theta, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter}
    )


def fit_mfgp(
    X: FloatArray,
    levels: IntArray,
    y: FloatArray,
    n_levels: int,
    *,
    rng: np.random.Generator,
    restarts: int = 8,
    fixed: Hyperparameters | None = None,
) -> MFGP:
    """Fit the multifidelity GP by MAP and condition it on the data.

    Parameters
    ----------
    X : ndarray of shape (n, d)
        Inputs (reduced embeddings). Repeats and several levels at one x are fine.
    levels : int ndarray of shape (n,)
        Fidelity level of each observation, in [0, n_levels).
    y : ndarray of shape (n,)
        Observed metric.
    n_levels : int
        L + 1. Levels without observations keep their prior-mode hyperparameters.
    rng : numpy.random.Generator
        Draws the restart points; the only source of randomness.
    restarts : int
        Number of L-BFGS-B starts: one from the prior mode, ``restarts - 1`` from
        ``_Priors.sample_start``. Each runs 30 iterations; the best two then run to
        convergence, and the best MAP objective wins.
    fixed : Hyperparameters, optional
        If given, no training: the returned GP conditions on the data with these.

    Returns
    -------
    MFGP

    Raises
    ------
    GPFitError
        Bad data (message names the row), or no restart reached a finite objective.
    """
    if n_levels < 1:
        raise GPFitError(f"n_levels must be >= 1, got {n_levels}")
    X, levels, y = _check_data(X, levels, y, n_levels)
    if fixed is not None:
        return MFGP(X, levels, y, n_levels, fixed)
    if restarts < 1:
        raise GPFitError(f"restarts must be >= 1, got {restarts}")

    ybar, ystd = _standardise(y)
    priors = _Priors.for_data(X, n_levels)
    objective = _MAPObjective(X, levels, (y - ybar) / ystd, n_levels, priors)
    bounds = list(zip(priors.lower, priors.upper, strict=True))
    starts = [priors.mode] + [priors.sample_start(rng) for _ in range(restarts - 1)]

    # Restarts in two stages: every start gets a short L-BFGS-B run, then the best
    # _N_POLISH of them continue to convergence. All `restarts` starts still compete for
    # the basin; the expensive tail of the optimisation is spent only on the leaders.
    # (Measured at n = 200, d = 12: full runs take ~140 evaluations each and nearly all
    # end in the same optimum, so this halves the fit time at no cost in objective.)
    # One BLAS thread: the matrices are a few hundred wide, where OpenBLAS threads only
    # add synchronisation (measured 30x slower Cholesky at n = 200 on a busy 2-core box).
    with threadpool_limits(limits=1, user_api="blas"):
        screened = [_minimize(objective, t, bounds, _SCREEN_ITER) for t in starts]
        finite = [r for r in screened if np.isfinite(r.fun)]
        finite.sort(key=lambda r: float(r.fun))
        polished = [_minimize(objective, r.x, bounds, _MAXITER) for r in finite[:_N_POLISH]]
    best_theta, best_f = None, math.inf
    for res in finite + polished:
        if np.isfinite(res.fun) and res.fun < best_f:
            best_theta, best_f = res.x, float(res.fun)
    if best_theta is None:
        raise GPFitError(
            f"MAP training failed from all {restarts} starts (non-finite objective); "
            "check X and y for extreme values or pass fixed hyperparameters"
        )

    K, _, _ = objective.covariance(best_theta)
    L, _ = _cholesky(K)
    mean, _ = objective.gls_mean(L)
    hp = _hyperparameters(best_theta, mean, X.shape[1], n_levels, ybar, ystd)
    return MFGP(X, levels, y, n_levels, hp)


# ----------------------------------------------------------------------------- posterior


class MFGP:
    """The multifidelity GP conditioned on observations; implements ``posterior.Posterior``.

    All inputs and outputs are in natural units. Construction factorises K once; every
    query then costs a kernel evaluation against the n training observations and a
    triangular solve with the stored factor. Picklable (plain numpy attributes).

    Parameters
    ----------
    X : ndarray of shape (n, d)
    levels : int ndarray of shape (n,)
    y : ndarray of shape (n,)
    n_levels : int
    hyperparameters : Hyperparameters

    Attributes
    ----------
    hyperparameters : Hyperparameters
    n_levels : int
    n_obs_per_level : int ndarray of shape (n_levels,)
    log_marginal_likelihood : float
        log N(y | mean, K), natural units.
    log_posterior : float
        log_marginal_likelihood + log prior, the prior evaluated on the standardised
        parameters (the MAP objective up to the constant n log std(y)); -inf when a noise
        variance is 0.
    jitter : float
        Absolute jitter that the Cholesky factorisation needed (usually 0).
    X_train, levels_train, y_train : ndarray
        The observations conditioned on.
    """

    def __init__(
        self,
        X: FloatArray,
        levels: IntArray,
        y: FloatArray,
        n_levels: int,
        hyperparameters: Hyperparameters,
    ) -> None:
        X, levels, y = _check_data(X, levels, y, n_levels)
        hp = hyperparameters
        if hp.n_levels != n_levels or hp.d != X.shape[1]:
            raise GPFitError(
                f"hyperparameters are for {hp.n_levels} level(s) and d = {hp.d}, but the "
                f"data have n_levels = {n_levels} and d = {X.shape[1]}; refit, or pass "
                "hyperparameters fitted on the same study"
            )
        self.hyperparameters = hp
        self.n_levels = int(n_levels)
        self.X_train = X
        self.levels_train = levels
        self.y_train = y
        self.n_obs_per_level = np.bincount(levels, minlength=n_levels)
        # Stationary kernels: centring changes nothing but the rounding of the matmul
        # distance formula (kernels.scaled_sqdist).
        self._shift = X.mean(axis=0)
        self._Xt = X - self._shift
        self._s = np.concatenate([[hp.outputscale0], hp.outputscales])
        self._ell = np.vstack([hp.lengthscales0[None, :], hp.lengthscales])

        n = X.shape[0]
        with np.errstate(over="ignore", invalid="ignore"):  # _cholesky reports non-finite K
            K = self._k_aug(self._Xt, levels, self._Xt, levels, exact=True)
        K[np.diag_indices(n)] += hp.noise[levels]
        with threadpool_limits(limits=1, user_api="blas"):  # small matrix: see fit_mfgp
            self._L, self.jitter = _cholesky(K)
        r = y - hp.mean
        self._alpha = cho_solve((self._L, True), r, check_finite=False)  # GPML Alg. 2.1 l. 3
        self.log_marginal_likelihood = float(
            -0.5 * r @ self._alpha - np.sum(np.log(np.diag(self._L))) - 0.5 * n * _LOG_2PI
        )  # GPML Alg. 2.1 line 7

        ybar, ystd = _standardise(y)
        v = ystd**2
        theta_std = _pack(
            Hyperparameters(
                mean=0.0,
                outputscale0=hp.outputscale0 / v,
                lengthscales0=hp.lengthscales0,
                outputscales=hp.outputscales / v,
                lengthscales=hp.lengthscales,
                noise=hp.noise / v,
            )
        )
        if np.all(np.isfinite(theta_std)):
            lp, _ = _Priors.for_data(X, n_levels).log_prior(theta_std)
        else:
            lp = -math.inf
        self.log_posterior = self.log_marginal_likelihood + lp

    # ------------------------------------------------------------------ helpers

    @property
    def lengthscales0(self) -> FloatArray:
        """Level-0 (theta0) lengthscales, shape (d,)."""
        return self.hyperparameters.lengthscales0

    def _centre(self, X: Any, name: str = "X") -> FloatArray:
        X = np.asarray(X, dtype=np.float64)
        d = self._shift.size
        if X.ndim != 2 or X.shape[1] != d:
            raise ValueError(f"{name} must have shape (n, {d}), got shape {X.shape}")
        return X - self._shift

    def _levels(self, levels: Any, n: int, name: str = "levels") -> IntArray:
        return _check_levels(levels, self.n_levels, n, name)

    def _k0(self, A: FloatArray, B: FloatArray) -> FloatArray:
        """k0 between centred point sets, (len(A), len(B))."""
        return matern52(A, B, self._ell[0], self._s[0])

    def _k_aug(
        self, A: FloatArray, la: IntArray, B: FloatArray, lb: IntArray, *, exact: bool = False
    ) -> FloatArray:
        """k_aug((A, la), (B, lb)) = k0 + [a == b >= 1] k_a, centred inputs; paper sec. 3."""
        K = matern52(A, B, self._ell[0], self._s[0], exact=exact)
        for lv in range(1, self.n_levels):
            ia = np.flatnonzero(la == lv)
            ib = np.flatnonzero(lb == lv)
            if ia.size and ib.size:
                K[np.ix_(ia, ib)] += matern52(A[ia], B[ib], self._ell[lv], self._s[lv], exact=exact)
        return K

    def _solve_L(self, B: FloatArray) -> FloatArray:
        """L^-1 B for B of shape (n, m); overwrites B."""
        return solve_triangular(self._L, B, lower=True, overwrite_b=True, check_finite=False)

    def _obs_factor(self, Xc: FloatArray, lc: IntArray) -> FloatArray:
        """W = L^-1 k_aug(Y_n, (Xc, lc)), shape (n, m), for centred Xc."""
        return self._solve_L(self._k_aug(self._Xt, self.levels_train, Xc, lc))

    def _predict_block(self, Xc: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and (unclipped) variance of theta0 at centred rows Xc.

        Paper sec. 2 (GP predictions) with the constant mean; GPML Alg. 2.1.
        """
        k = self._k0(Xc, self._Xt)  # (m, n), C order
        mu = self.hyperparameters.mean + k @ self._alpha  # GPML Alg. 2.1 line 4
        v = self._solve_L(k.T)  # F-ordered view: LAPACK solves in place, no copy
        sigma2 = self._s[0] - np.einsum("ij,ij->j", v, v)  # GPML Alg. 2.1 lines 5-6
        return mu, sigma2

    def _chunk_rows(self, chunk_size: int) -> int:
        return max(1, min(int(chunk_size), _CHUNK_ELEMENTS // max(1, self._Xt.shape[0])))

    # --------------------------------------------------------------- public API

    def predict_theta0(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and variance of theta0 (noise-free level-0 metric) at X.

        Parameters
        ----------
        X : ndarray of shape (m, d)

        Returns
        -------
        mu : ndarray of shape (m,)
        sigma2 : ndarray of shape (m,)
            Clipped at 0: rounding can make k0(x,x) - v'v slightly negative at observed
            points when the level-0 noise is tiny.
        """
        mu, sigma2, _ = self._score(self._centre(X), np.empty(0), 50_000)
        return mu, sigma2

    def cov_theta0(self, Xa: FloatArray, Xb: FloatArray) -> FloatArray:
        """Posterior covariance cov_n(theta0(xa), theta0(xb)).

        k0(Xa, Xb) - k0(Xa, X_n) K^-1 k0(X_n, Xb).

        Parameters
        ----------
        Xa : ndarray of shape (na, d)
        Xb : ndarray of shape (nb, d)

        Returns
        -------
        C : ndarray of shape (na, nb)
        """
        A, B = self._centre(Xa, "Xa"), self._centre(Xb, "Xb")
        Va = self._solve_L(self._k0(self._Xt, A))
        Vb = self._solve_L(self._k0(self._Xt, B))
        return self._k0(A, B) - Va.T @ Vb

    def cov_theta0_obs(self, X: FloatArray, Xc: FloatArray, levels: IntArray) -> FloatArray:
        """cov_n(theta0(x), y_c) for pool points x and candidate observations c = (x_c, l).

        cov_n(theta0(x), y_c) = k0(x, x_c) - k0(x, X_n) K^-1 k_aug(Y_n, (x_c, l))
        (DESIGN.md). theta0 is noise-free and alpha_l is independent of theta0, so the
        prior part is k0 alone whatever the candidate's level.

        Parameters
        ----------
        X : ndarray of shape (n, d)
        Xc : ndarray of shape (m, d)
        levels : int ndarray of shape (m,)

        Returns
        -------
        C : ndarray of shape (n, m)
        """
        A, B = self._centre(X), self._centre(Xc, "Xc")
        lc = self._levels(levels, B.shape[0])
        V = self._solve_L(self._k0(self._Xt, A))
        W = self._obs_factor(B, lc)
        return self._k0(A, B) - V.T @ W

    def cov_obs_obs(
        self,
        Xa: FloatArray,
        levels_a: IntArray,
        Xb: FloatArray,
        levels_b: IntArray,
        same: NDArray[np.bool_] | None = None,
    ) -> FloatArray:
        """cov_n(y_a, y_b) between two sets of candidate observations.

        k_aug((xa, a), (xb, b)) + [same] tau_a^2 - k_aug((xa, a), Y_n) K^-1 k_aug(Y_n, (xb, b)).

        Parameters
        ----------
        Xa : ndarray of shape (na, d)
        levels_a : int ndarray of shape (na,)
        Xb : ndarray of shape (nb, d)
        levels_b : int ndarray of shape (nb,)
        same : bool ndarray of shape (na, nb), optional
            True where a and b are the same future observation (noise added). None means
            identical coordinates and identical level.

        Returns
        -------
        G : ndarray of shape (na, nb)
        """
        A, B = self._centre(Xa, "Xa"), self._centre(Xb, "Xb")
        # Parameter names follow posterior.Posterior (callers may pass them by keyword).
        la = self._levels(levels_a, A.shape[0], "levels_a")
        lb = self._levels(levels_b, B.shape[0], "levels_b")
        if same is None:
            same = _same_observation(np.asarray(Xa, float), la, np.asarray(Xb, float), lb)
        else:
            same = np.asarray(same, dtype=bool)
            if same.shape != (A.shape[0], B.shape[0]):
                raise ValueError(
                    f"same must have shape ({A.shape[0]}, {B.shape[0]}), got {same.shape}"
                )
        G = self._k_aug(A, la, B, lb) - self._obs_factor(A, la).T @ self._obs_factor(B, lb)
        ia, ib = np.nonzero(same)
        G[ia, ib] += self.hyperparameters.noise[la[ia]]
        return G

    def obs_var(self, Xc: FloatArray, levels: IntArray) -> FloatArray:
        """var_n(y_c) including the noise tau_l^2 of the candidate's level.

        Parameters
        ----------
        Xc : ndarray of shape (m, d)
        levels : int ndarray of shape (m,)

        Returns
        -------
        v : ndarray of shape (m,)
            Clipped at 0.
        """
        B = self._centre(Xc, "Xc")
        lc = self._levels(levels, B.shape[0])
        prior = self._s[0] + np.where(lc >= 1, self._s[lc], 0.0) + self.hyperparameters.noise[lc]
        W = self._obs_factor(B, lc)
        return np.maximum(prior - np.einsum("ij,ij->j", W, W), 0.0)

    def score(
        self, X: FloatArray, gammas: Any, chunk_size: int = 50_000
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Posterior mean, sd and failure probability p_n(x) = Phi((gamma - mu) / sd).

        p_n(x) = E_{theta_n}[1{theta_n(x) <= gamma}] (paper eq. (2) and the line after
        it), with theta_n(x) ~ N(mu, sd^2). Computed in chunks of rows so
        the (chunk, n_obs) kernel block stays bounded (at most ``chunk_size`` rows and
        2^24 kernel entries, ~128 MB, per chunk) for pools of millions.

        Parameters
        ----------
        X : ndarray of shape (m, d)
        gammas : array-like of shape (g,)
            Failure thresholds.
        chunk_size : int
            Maximum rows per chunk.

        Returns
        -------
        mu : ndarray of shape (m,)
        sd : ndarray of shape (m,)
            sqrt of the clipped variance.
        p : ndarray of shape (m, g)
            Where sd is exactly 0 (clipped variance of an observed noise-free point),
            p = 1{mu <= gamma}, the limit of Phi as sd -> 0 (never NaN).
        """
        g = np.atleast_1d(np.asarray(gammas, dtype=np.float64))
        if g.ndim != 1:
            raise ValueError(f"gammas must be one-dimensional, got shape {g.shape}")
        mu, sigma2, p = self._score(self._centre(X), g, chunk_size)
        return mu, np.sqrt(sigma2), p

    def _score(
        self, X: FloatArray, gammas: FloatArray, chunk_size: int
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """mu (m,), clipped sigma2 (m,), p (m, len(gammas)) for centred X, chunk by chunk."""
        m = X.shape[0]
        mu = np.empty(m)
        sigma2 = np.empty(m)
        p = np.empty((m, gammas.size))
        step = self._chunk_rows(chunk_size)
        for start in range(0, m, step):
            sl = slice(start, min(start + step, m))
            mu[sl], s2 = self._predict_block(X[sl])
            sigma2[sl] = np.maximum(s2, 0.0)
            if gammas.size:
                p[sl] = _failure_probability(mu[sl], np.sqrt(sigma2[sl]), gammas)
        return mu, sigma2, p


def _failure_probability(mu: FloatArray, sd: FloatArray, gammas: FloatArray) -> FloatArray:
    """Phi((gamma - mu) / sd), shape (m, g); 1{mu <= gamma} where sd == 0."""
    diff = gammas[None, :] - mu[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        p = ndtr(diff / sd[:, None])
    zero = sd == 0.0
    if zero.any():
        p[zero] = (diff[zero] >= 0.0).astype(np.float64)
    return p


def _same_observation(
    Xa: FloatArray, la: IntArray, Xb: FloatArray, lb: IntArray
) -> NDArray[np.bool_]:
    """[i, j] True where (Xa[i], la[i]) and (Xb[j], lb[j]) are identical (exact equality).

    Rows are mapped to integer ids with np.unique, so memory is O(na nb), not O(na nb d).
    """
    rows = np.concatenate([np.column_stack([Xa, la]), np.column_stack([Xb, lb])]) + 0.0
    _, ids = np.unique(rows, axis=0, return_inverse=True)
    ids = ids.reshape(-1)
    return ids[: len(Xa), None] == ids[None, len(Xa) :]
