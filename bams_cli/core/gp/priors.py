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
  (standardised) when that is larger than 0.01 (``pair_moments``). The pairs are the
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
- scale rho_l of a cheap level against level 0 (``Hyperparameters.scales``): log-sd 0.5
  about the level's pairs' least-squares slope (rho within 0.37..2.7 times it at two
  sds). A level whose values are a multiple of level 0's (a coarser physics step that
  scales every distance, a simulator in feet, a cheaper model's margin on another scale)
  is the case for it, since with the additive model such a level's difference from level
  0 is a large discrepancy and the level looks weak. The data are then standardised with
  that level's values put into level 0's units along the pairs' line
  (``level0_standardise``), so every other prior is in level 0's units whatever units the
  level reports: times 1/50, 8 or 40, the same level gives the same discrepancy and level-0
  posterior, its scale moving with the units (until 2026-11-29 the scale's mode was 1 and
  the units those of all levels pooled: a level 20x level 0's was fitted at rho 1.1, its
  discrepancy 25 times theta0's signal). rho is free only where the level's pairs show a
  scale (``shows_scale``: five or more pairs at correlation >= 0.9 whose least-squares
  slope cuts the sd of their differences by 4 or more, sd(y_l - y_0) >= 4 sd(y_l - slope
  y_0)); elsewhere it stays 1, the additive model. Why so strict: free wherever three
  pairs existed (prior log-sd 0.5), the suite's weak levels got scales from 0.52 to 2.01
  off a handful of pairs, and on rare_regions the discrepancy fell below half the truth
  on three seeds of ten (two screened for it), digits on one; the level-tracking
  problems fitted 0.93-1.08, which the additive model holds as well. Gated on five pairs
  at correlation 0.9 and a slope 1.5x from 1, digits (corr(f0, f1) 0.69 over the pool)
  still freed it on four seeds of ten (1.55-2.01; its few pairs, at failures and far from
  them, correlate closely), at a discrepancy 0.51-0.55 of the truth; their pairs' slopes
  (1.9-2.2 at 5-10 pairs, correlation 0.96-0.99) cut the sd of the differences by
  2.1-3.8, a cut of 2 still let one seed of ten through (1.84, a discrepancy 0.55 of
  the truth). The fresh problem ``common`` (the cheap level 2.5 x level 0 + 1 + a small
  bias; docs/suite/fresh_problems.py) shows cuts of 5.0-8.3 at its 7 pairs after three
  batches, the breast-cancer problem (a weaker model as the cheap level) 1.0-1.7. At a
  slope of 2 a cut of 4 needs pairs at correlation 0.992; a cheap level that reports
  other units (100x) passes at any usable correlation. A level the gate leaves at 1 is
  left to the discrepancy, which then trusts it less, not more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from bams_cli.core.gp._numerics import LOG_2PI, FloatArray, IntArray, input_ranges, standardise

#: Pairs (level 0 and a cheap level at the same input) needed before their variance
#: moves the discrepancy prior.
MIN_PAIRS = 3
#: A cheap level's scale is fitted only where its pairs show one: this many pairs, ...
SCALE_PAIRS = 5
#: ... whose values correlate this closely (a weak level's slope is its correlation times
#: a ratio of sds, not a scale), ...
SCALE_CORR = 0.9
#: ... at a slope that cuts the sd of their differences by this factor or more
#: (``shows_scale``; module docstring).
SCALE_GAIN = 4.0


def paired_differences(
    seg: IntArray, levels: IntArray, y: FloatArray, level: int, scale: float = 1.0
) -> FloatArray:
    """y_l - scale y_0 for every segment observed at both levels (repeats averaged first).

    Parameters
    ----------
    seg : int ndarray of shape (n,)
        Segment (pool row) of each observation.
    levels : int ndarray of shape (n,)
    y : ndarray of shape (n,)
    level : int
        The cheap level l >= 1.
    scale : float
        rho_l (``Hyperparameters.scales``): y_l - rho_l y_0 is what a scaled level's pairs
        measure of its discrepancy.

    Returns
    -------
    d : ndarray of shape (k,), in increasing segment order
    """
    y0, yl = paired_values(seg, levels, y, level)
    return yl - scale * y0


def paired_values(
    seg: IntArray, levels: IntArray, y: FloatArray, level: int
) -> tuple[FloatArray, FloatArray]:
    """(y_0, y_l) of every segment observed at both levels, repeats averaged first, in
    increasing segment order (``paired_differences``)."""
    out = []
    for lv in (0, level):
        m = levels == lv
        keys, inv = np.unique(seg[m], return_inverse=True)
        means = np.bincount(inv, weights=y[m]) / np.bincount(inv)
        out.append((keys, means))
    (k0, m0), (kl, ml) = out
    _, i0, il = np.intersect1d(k0, kl, return_indices=True)
    return m0[i0], ml[il]


#: ``pair_evidence``: differences y_l - y_0 whose variance is under this share of level
#: 0's are a constant offset (a cheap level that is level 0 shifted), whatever rounding
#: says of their sd.
EXACT_OFFSET = 1e-12


def shows_scale(k: int, slope: float, corr: float, sd_ratio: float) -> bool:
    """Whether k pairs measure a scale: enough of them (``SCALE_PAIRS``), tracking
    closely (``SCALE_CORR``), at a positive slope that cuts the sd of what they show,
    sd(y_l - y_0) over sd(y_l - slope y_0) = ``sd_ratio``, by ``SCALE_GAIN`` or more."""
    return k >= SCALE_PAIRS and corr >= SCALE_CORR and slope > 0 and sd_ratio >= SCALE_GAIN


def pair_evidence(y0: FloatArray, yl: FloatArray) -> tuple[int, float, float, float]:
    """(pairs, least-squares slope of y_l on y_0, their correlation, sd(y_l - y_0) over
    sd(y_l - slope y_0)) over pairs: what ``shows_scale`` judges. From one covariance
    (a = var y_l, b = var y_0, c = cov): slope c / b, the two variances a - 2c + b and
    a - c^2 / b. NaN below two pairs or where either level's values do not vary; the
    ratio inf on an exact line of another slope, and 1 where y_l - y_0 is constant to
    within ``EXACT_OFFSET`` of level 0's variance (slope 1 already fits exactly: both sds
    are rounding, and their ratio would be any number)."""
    k = int(y0.size)
    if k < 2 or np.ptp(y0) == 0 or np.ptp(yl) == 0:
        return k, math.nan, math.nan, math.nan
    (a, c), (_, b) = np.cov(yl, y0)
    rest = a - c * c / b
    diff = a - 2.0 * c + b
    if diff <= EXACT_OFFSET * b:
        ratio = 1.0
    else:
        ratio = math.sqrt(diff / rest) if rest > 0 else math.inf
    return k, float(c / b), float(c / math.sqrt(a * b)), ratio


def pair_lines(
    X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int
) -> list[tuple[float, float] | None]:
    """Each cheap level's pairs' least-squares line y_l = slope y_0 + intercept where they
    show a scale (``shows_scale``), else None."""
    _, seg = np.unique(np.asarray(X), axis=0, return_inverse=True)
    out: list[tuple[float, float] | None] = []
    for lv in range(1, n_levels):
        y0, yl = paired_values(seg.ravel(), levels, y, lv)
        k, slope, corr, gain = pair_evidence(y0, yl)
        shown = shows_scale(k, slope, corr, gain)
        out.append((slope, float(np.mean(yl) - slope * np.mean(y0))) if shown else None)
    return out


def pair_scales(X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int) -> list[float]:
    """Each cheap level's pairs' slope where they show a scale (``shows_scale``), else NaN:
    the levels whose scale ``fit_mfgp`` frees, and where its search starts."""
    return [math.nan if ln is None else ln[0] for ln in pair_lines(X, levels, y, n_levels)]


def in_level0_units(
    levels: IntArray, y: FloatArray, lines: list[tuple[float, float] | None]
) -> FloatArray:
    """y with every cheap level whose pairs show a scale put into level 0's units along
    its pairs' line, (y_l - intercept) / slope (``pair_lines``); the rest as it is.

    What the data are standardised by (``level0_standardise``): the priors are in
    standardised units, and a cheap level that reports other units (20x level 0's, say)
    would otherwise set them, putting level 0's whole variation at 1/400 of the unit and
    its noise prior's mode at a third of it.
    """
    if all(ln is None for ln in lines):
        return y
    out = np.array(y, dtype=np.float64, copy=True)
    for lv, ln in enumerate(lines, start=1):
        if ln is not None:
            m = levels == lv
            out[m] = (out[m] - ln[1]) / ln[0]
    return out


def pair_moments(
    X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int
) -> list[tuple[float, float, float] | None]:
    """(var y_l, var y_0, cov(y_l, y_0)) over each cheap level's pairs (unbiased), None
    below ``MIN_PAIRS`` pairs: what the pairs say of y_l - rho y_0 at any scale rho,
    var = var y_l - 2 rho cov + rho^2 var y_0 (``_Priors.log_prior``)."""
    _, seg = np.unique(np.asarray(X), axis=0, return_inverse=True)
    out: list[tuple[float, float, float] | None] = []
    for lv in range(1, n_levels):
        y0, yl = paired_values(seg.ravel(), levels, y, lv)
        if y0.size < MIN_PAIRS:
            out.append(None)
            continue
        c = np.cov(yl, y0, ddof=1)
        out.append((float(c[0, 0]), float(c[1, 1]), float(c[0, 1])))
    return out


def level0_standardise(
    X: FloatArray, levels: IntArray, y: FloatArray, n_levels: int
) -> tuple[float, float]:
    """(mean, std) the GP's data are standardised by: ``standardise`` over the values in
    level 0's units (``in_level0_units``), so a cheap level's units do not set the
    priors'. The same as ``standardise(y)`` where no level's pairs show a scale."""
    lines = pair_lines(X, levels, y, n_levels) if n_levels > 1 else []
    return standardise(in_level0_units(levels, y, lines))


@dataclass(frozen=True)
class PriorSpec:
    """Modes and log-space sds of the LogNormal priors, in standardised units.

    Each pair is (mode, log-sd); the module docstring says why each default is what it is.
    ``lengthscale_dim_scaling`` multiplies the lengthscale prior's location by sqrt(d)
    (BoTorch's dimension-scaled prior); ``discrepancy_from_pairs`` moves a cheap level's
    discrepancy mode to its pairs' variance and ``scale_from_pairs`` its scale's mode to
    their slope (module docstring). Turning any of them off is for experiments only.
    """

    outputscale0: tuple[float, float] = (1.0, 1.5)
    discrepancy: tuple[float, float] = (0.01, 1.0)
    noise0: tuple[float, float] = (3e-4, 1.0)
    noise: tuple[float, float] = (3e-3, 2.0)
    level_scale: tuple[float, float] = (1.0, 0.5)
    lengthscale_scale: float = math.sqrt(3.0)
    lengthscale_dim_scaling: bool = True
    discrepancy_from_pairs: bool = True
    #: Centre a cheap level's scale prior on its pairs' slope where they show a scale
    #: (``shows_scale``); False: on ``level_scale``'s mode everywhere (experiments only;
    #: the data are still standardised in level 0's units, ``level0_standardise``).
    scale_from_pairs: bool = True
    #: The discrepancy modes, one per cheap level, once resolved from a study's pairs
    #: (``with_pair_modes``); None: from ``discrepancy`` and whatever data ``for_data``
    #: is given.
    discrepancy_modes: tuple[float, ...] | None = None
    #: The pairs' moments behind those modes (``pair_moments``), one entry per cheap
    #: level (None: too few pairs): the mode at a scale rho other than 1 follows them.
    pair_moments: tuple[tuple[float, float, float] | None, ...] | None = None
    #: The scales' modes, one per cheap level, once resolved (``with_pair_modes``): the
    #: pairs' slope where they show a scale (``shows_scale``), else ``level_scale``'s.
    scale_modes: tuple[float, ...] | None = None


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
    moments: tuple[tuple[float, float, float] | None, ...] = (None,) * (n_levels - 1)
    if spec.discrepancy_from_pairs and n_levels > 1:
        moments = tuple(pair_moments(X, levels, y_std, n_levels))
        for lv, mom in enumerate(moments, start=1):
            if mom is not None:
                a, b, c = mom
                modes[lv - 1] = max(modes[lv - 1], a - 2.0 * c + b)  # var(y_l - y_0)
    # A slope is the same in standardised and natural units (one affine map for all).
    slopes = pair_scales(X, levels, y_std, n_levels) if spec.scale_from_pairs else []
    slopes += [math.nan] * (n_levels - 1 - len(slopes))
    scale_modes = tuple(spec.level_scale[0] if math.isnan(s) else float(s) for s in slopes)
    return replace(
        spec,
        discrepancy_modes=tuple(float(m) for m in modes),
        pair_moments=moments,
        scale_modes=scale_modes,
    )


def _per_level(
    resolved: tuple[float, ...] | None, default: float, n_levels: int, what: str
) -> FloatArray:
    """One mode per cheap level: those resolved from the study's pairs, else ``default``."""
    if resolved is None:
        return np.full(n_levels - 1, default)
    modes = np.asarray(resolved, dtype=np.float64)
    if modes.size != n_levels - 1:
        raise ValueError(f"{modes.size} {what} mode(s) resolved for {n_levels - 1} cheap level(s)")
    return modes


# Box bounds on the standardised parameters. Wide: the priors do the regularising; the
# bounds only keep L-BFGS-B away from overflow and from singular K.
_OUTPUTSCALE0_BOUNDS = (1e-4, 1e4)
_DISCREPANCY_BOUNDS = (1e-6, 1e4)
_LENGTHSCALE_BOUNDS = (5e-3, 1e3)  # in units of the training range of each dimension
_NOISE_BOUNDS = (1e-9, 1e1)
_LEVEL_SCALE_BOUNDS = (0.02, 50.0)  # times the scale's mode


@dataclass(frozen=True)
class _Priors:
    """Independent LogNormal(loc, scale) priors on exp(theta), and box bounds on theta.

    All arrays have the layout of ``_pack``. Standardised units.
    """

    loc: FloatArray
    scale: FloatArray
    lower: FloatArray
    upper: FloatArray
    #: Trailing entries that are cheap levels' scales (``sample_start`` starts them at
    #: the mode).
    n_scales: int = 0
    #: Per cheap level, the pairs' (var y_l, var y_0, cov) and the floor of its
    #: discrepancy mode; a level without them keeps its fixed mode (``log_prior``).
    pair_moments: tuple[tuple[float, float, float] | None, ...] = ()
    discrepancy_floor: float = 0.01

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
        disc_modes = _per_level(spec.discrepancy_modes, spec.discrepancy[0], m, "discrepancy")
        scale_modes = _per_level(spec.scale_modes, spec.level_scale[0], m, "scale")
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
                [from_mode(v, spec.level_scale[1]) for v in scale_modes],
            ]
        )
        scale = np.concatenate(
            [
                [spec.outputscale0[1]],
                np.full(m - 1, spec.discrepancy[1]),
                np.full(m * d, spec.lengthscale_scale),
                [spec.noise0[1]],
                np.full(m - 1, spec.noise[1]),
                np.full(m - 1, spec.level_scale[1]),
            ]
        )
        lower = np.log(
            np.concatenate(
                [
                    [_OUTPUTSCALE0_BOUNDS[0]],
                    np.full(m - 1, _DISCREPANCY_BOUNDS[0]),
                    np.tile(_LENGTHSCALE_BOUNDS[0] * np.exp(log_range), m),
                    np.full(m, _NOISE_BOUNDS[0]),
                    _LEVEL_SCALE_BOUNDS[0] * scale_modes,
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
                    _LEVEL_SCALE_BOUNDS[1] * scale_modes,
                ]
            )
        )
        moments = spec.pair_moments if spec.pair_moments is not None else (None,) * (m - 1)
        if len(moments) != m - 1:
            raise ValueError(f"{len(moments)} pair moment(s) resolved for {m - 1} cheap level(s)")
        return cls(
            loc=loc, scale=scale, lower=lower, upper=upper, n_scales=m - 1,
            pair_moments=tuple(moments), discrepancy_floor=float(spec.discrepancy[0]),
        )  # fmt: skip

    @property
    def mode(self) -> FloatArray:
        """theta at the prior mode, clipped to the bounds."""
        return np.clip(self.loc - self.scale**2, self.lower, self.upper)

    def sample_start(self, rng: np.random.Generator) -> FloatArray:
        """A restart point: theta ~ N(mode, scale^2), clipped to the bounds.

        Centred on the mode rather than the median: the lengthscale prior's median
        (4.1 sqrt(d) x range) is far beyond where the MAP usually lands. The cheap levels'
        scales start at their mode: one smooth dimension each, which every start then
        finds from there (and the draws for the rest are those of a model without them).
        """
        mode = self.loc - self.scale**2
        k = mode.size - self.n_scales
        start = np.concatenate([rng.normal(mode[:k], self.scale[:k]), mode[k:]])
        return np.clip(start, self.lower, self.upper)

    def discrepancy_mode_at(self, level: int, rho: float) -> float:
        """The mode of cheap level ``level``'s (1-based index - 1) discrepancy variance at
        scale rho: its pairs' var(y_l - rho y_0) / rho^2 or the floor, whichever is
        larger; the fixed mode where it has no pairs (``log_prior``)."""
        mom = self.pair_moments[level] if level < len(self.pair_moments) else None
        if mom is None:
            return math.exp(self.loc[1 + level] - self.scale[1 + level] ** 2)
        a, b, c = mom
        return max(a / rho**2 - 2.0 * c / rho + b, self.discrepancy_floor)

    def log_prior(self, theta: FloatArray) -> tuple[float, FloatArray]:
        """Sum of LogNormal log densities of exp(theta) and its gradient wrt theta.

        log p(v) = -log v - log(scale sqrt(2 pi)) - (log v - loc)^2 / (2 scale^2), v = exp(theta).

        A cheap level with pairs has its discrepancy's mode at what the pairs show at the
        level's scale rho: the variance of y_l - rho y_0 in level 0's units,
        v(rho) = (var y_l - 2 rho cov + rho^2 var y_0) / rho^2 (at rho = 1 the variance of
        y_l - y_0), or the fixed floor where that is smaller. It is then a prior on the
        discrepancy given rho, and its location's derivative in log rho enters the scale's
        gradient.
        """
        loc = self.loc
        dloc = []  # (discrepancy index, scale index, d loc / d log rho)
        if any(mom is not None for mom in self.pair_moments):
            loc = loc.copy()
            first_scale = self.loc.size - self.n_scales
            for i, mom in enumerate(self.pair_moments):
                if mom is None:
                    continue
                a, b, c = mom
                rho = math.exp(theta[first_scale + i])
                v = self.discrepancy_mode_at(i, rho)
                loc[1 + i] = math.log(v) + self.scale[1 + i] ** 2
                if v > self.discrepancy_floor:
                    dloc.append((1 + i, first_scale + i, (-2.0 * a / rho**2 + 2.0 * c / rho) / v))
        u = (theta - loc) / self.scale
        value = float(np.sum(-theta - np.log(self.scale) - 0.5 * LOG_2PI - 0.5 * u * u))
        grad = -1.0 - u / self.scale
        for i_disc, i_rho, dl in dloc:
            grad[i_rho] += u[i_disc] / self.scale[i_disc] * dl
        return value, grad
