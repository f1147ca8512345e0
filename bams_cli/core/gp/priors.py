"""Priors of the multifidelity GP's hyperparameters, every default defined once.

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
  Pairs move the mode: once ``MIN_PAIRS`` segments have been run at level 0 and at the
  cheap level, the mode is the sample variance of their differences y_l - y_0
  (standardised) when that is larger than 0.01 (``pair_variances``). The pairs are the
  one direct measurement of the discrepancy, but a handful of them against a hundred
  cheap-only runs could not pull the MAP away from a fixed mode of 0.01: on the suite's
  weak_cheap (corr(f0, f1) 0.59) the fitted sd of y1 - y0 was on average 0.69 of the truth, seeds
  down to 0.48, with the level-1 misfit left as noise; with the mode at the pairs'
  variance every suite problem's fitted sd is within 2x of the truth on 10 seeds of 10
  (docs/suite/evidence.md, "discrepancy-pairs"). The pairs enter the likelihood too, so
  they count twice; the log-sd of 1.0 around them is what keeps that honest, and where
  they show less than 0.01 the fixed mode stands (a constant bias is the GLS offset's,
  not the discrepancy's). What the pairs measure is the whole of y_l - y_0, discrepancy
  and both levels' noise, and the mode goes to the discrepancy: a cheap level whose
  difference is mostly noise is fitted as a rough discrepancy (a review's example: true
  discrepancy sd 0.07 and level-1 noise sd 0.4 gave a fitted discrepancy sd of 0.30-0.44
  and noise 0.03-0.04, where the fixed mode gave 0.06-0.12 and 0.27-0.41; level-0
  prediction error about the same). The sd of y_l - y_0 comes out right either way, and a
  discrepancy, which repeats nearby cannot average away, makes the model trust the cheap
  level less, not more. The pairs that set the mode are also the ones
  ``checks.check_model`` tests the fitted sd against, so that check is weaker than it was
  with the fixed mode (not measured).
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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from bams_cli.core.gp._numerics import LOG_2PI, FloatArray, IntArray, input_ranges

#: Pairs (level 0 and a cheap level at the same input) needed before their variance
#: moves the discrepancy prior.
MIN_PAIRS = 3


def paired_differences(seg: IntArray, levels: IntArray, y: FloatArray, level: int) -> FloatArray:
    """y_l - y_0 for every segment observed at both levels (repeats averaged first).

    Parameters
    ----------
    seg : int ndarray of shape (n,)
        Segment (pool row) of each observation.
    levels : int ndarray of shape (n,)
    y : ndarray of shape (n,)
    level : int
        The cheap level l >= 1.

    Returns
    -------
    d : ndarray of shape (k,), in increasing segment order
    """
    out = []
    for lv in (0, level):
        m = levels == lv
        keys, inv = np.unique(seg[m], return_inverse=True)
        means = np.bincount(inv, weights=y[m]) / np.bincount(inv)
        out.append((keys, means))
    (k0, m0), (kl, ml) = out
    _, i0, il = np.intersect1d(k0, kl, return_indices=True)
    return ml[il] - m0[i0]


def pair_variances(
    X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int
) -> list[tuple[int, float]]:
    """(number of pairs, variance of y_l - y_0 over them) for each cheap level l >= 1.

    A pair is an input observed at level 0 and at level l (identical rows of X stand for
    one segment; ``paired_differences``). The variance is the unbiased sample variance,
    NaN below two pairs.
    """
    _, seg = np.unique(np.asarray(X), axis=0, return_inverse=True)
    out = []
    for lv in range(1, n_levels):
        d = paired_differences(seg.ravel(), levels, y, lv)
        out.append((int(d.size), float(np.var(d, ddof=1)) if d.size >= 2 else math.nan))
    return out


@dataclass(frozen=True)
class PriorSpec:
    """Modes and log-space sds of the LogNormal priors, in standardised units.

    Each pair is (mode, log-sd); the module docstring says why each default is what it is.
    ``lengthscale_dim_scaling`` multiplies the lengthscale prior's location by sqrt(d)
    (BoTorch's dimension-scaled prior); ``discrepancy_from_pairs`` moves a cheap level's
    discrepancy mode to its pairs' variance (module docstring). Turning either off is for
    experiments only.
    """

    outputscale0: tuple[float, float] = (1.0, 1.5)
    discrepancy: tuple[float, float] = (0.01, 1.0)
    noise0: tuple[float, float] = (3e-4, 1.0)
    noise: tuple[float, float] = (3e-3, 2.0)
    lengthscale_scale: float = math.sqrt(3.0)
    lengthscale_dim_scaling: bool = True
    discrepancy_from_pairs: bool = True
    #: The discrepancy modes, one per cheap level, once resolved from a study's pairs
    #: (``with_pair_modes``); None: from ``discrepancy`` and whatever data ``for_data``
    #: is given.
    discrepancy_modes: tuple[float, ...] | None = None


#: The priors every fit uses unless told otherwise.
DEFAULT_PRIORS = PriorSpec()


def with_pair_modes(
    spec: PriorSpec | None, X: FloatArray, levels: IntArray, y_std: FloatArray, n_levels: int
) -> PriorSpec:
    """``spec`` with its discrepancy modes fixed from these observations' pairs.

    ``fit_mfgp`` and ``condition`` resolve the modes once, on every observation, and hand
    the result on: the search may run on a subset and the model may condition on one, and
    neither subset keeps the pairs, so the prior the model reports (``log_posterior``)
    must not be rebuilt from it. Already resolved: returned as it is.
    """
    spec = DEFAULT_PRIORS if spec is None else spec
    if spec.discrepancy_modes is not None:
        return spec
    modes = [spec.discrepancy[0]] * (n_levels - 1)
    if spec.discrepancy_from_pairs and n_levels > 1:
        for lv, (k, v) in enumerate(pair_variances(X, levels, y_std, n_levels), start=1):
            if k >= MIN_PAIRS and v > modes[lv - 1]:
                modes[lv - 1] = v
    return replace(spec, discrepancy_modes=tuple(float(m) for m in modes))


# Box bounds on the standardised parameters. Wide: the priors do the regularising; the
# bounds only keep L-BFGS-B away from overflow and from singular K.
_OUTPUTSCALE0_BOUNDS = (1e-4, 1e4)
_DISCREPANCY_BOUNDS = (1e-6, 1e4)
_LENGTHSCALE_BOUNDS = (5e-3, 1e3)  # in units of the training range of each dimension
_NOISE_BOUNDS = (1e-9, 1e1)


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
    def for_data(
        cls,
        X: FloatArray,
        n_levels: int,
        spec: PriorSpec | None = None,
    ) -> _Priors:
        """Priors for training inputs X of shape (n, d) and ``n_levels`` levels.

        A cheap level's discrepancy mode is ``spec.discrepancy_modes``' when resolved from
        the study's pairs (``with_pair_modes``), else ``spec.discrepancy``'s.
        """
        spec = DEFAULT_PRIORS if spec is None else spec
        d = X.shape[1]
        m = n_levels
        disc_modes = (
            np.full(m - 1, spec.discrepancy[0])
            if spec.discrepancy_modes is None
            else np.asarray(spec.discrepancy_modes, dtype=np.float64)
        )
        if disc_modes.size != m - 1:
            raise ValueError(
                f"{disc_modes.size} discrepancy mode(s) resolved for {m - 1} cheap level(s)"
            )
        log_range = np.log(input_ranges(X))

        def from_mode(mode: float, scale: float) -> float:
            # LogNormal(loc, scale) has its mode at exp(loc - scale^2).
            return math.log(mode) + scale**2

        # BoTorch's dimension-scaled lengthscale prior, on unit-cube lengthscales; moving
        # to natural units shifts loc by log(range) per dimension.
        dim_shift = 0.5 * math.log(d) if spec.lengthscale_dim_scaling else 0.0
        ell_loc = math.sqrt(2.0) + dim_shift + log_range
        loc = np.concatenate(
            [
                [from_mode(*spec.outputscale0)],
                [from_mode(v, spec.discrepancy[1]) for v in disc_modes],
                np.tile(ell_loc, m),
                [from_mode(*spec.noise0)],
                np.full(m - 1, from_mode(*spec.noise)),
            ]
        )
        scale = np.concatenate(
            [
                [spec.outputscale0[1]],
                np.full(m - 1, spec.discrepancy[1]),
                np.full(m * d, spec.lengthscale_scale),
                [spec.noise0[1]],
                np.full(m - 1, spec.noise[1]),
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
        value = float(np.sum(-theta - np.log(self.scale) - 0.5 * LOG_2PI - 0.5 * u * u))
        grad = -1.0 - u / self.scale
        return value, grad
