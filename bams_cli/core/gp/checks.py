"""Self-checks of a fitted model against its own data: is it overconfident?

A GP that is confidently wrong is the worst case for BAMS: the greedy stops running the
expensive level, and the rate estimate's weights and interval follow the model. Two checks
need nothing but the observations the model was fitted on (DESIGN.md, "Paired evidence"):

* Leave-one-out residuals at level-0 points, in closed form (Rasmussen and Williams 2006,
  sec. 5.4.2, eqs. 5.10-5.12): with alpha = K^-1 (y - H beta),

      y_i - mu_{-i} = alpha_i / [K^-1]_ii,      var_{-i} = 1 / [K^-1]_ii,

  so z_i = alpha_i / sqrt([K^-1]_ii) is N(0, 1) under the model. sum z_i^2 far above its
  chi-square(n) range means the model's intervals are too narrow where it was tested.
* Paired differences. A segment observed at level 0 and at level l gives
  d = y_l - rho_l y_0 = b_l + rho_l (alpha_l(x) + eps_l - eps_0) (rho_l = 1 but for a
  scaled level, ``Hyperparameters.scales``), whose variance over the pool under the
  model is rho_l^2 (s_l + tau_l^2 + tau_0^2) (the fitted discrepancy variance plus both
  noises). The pairs' sample variance S^2 (the offset b_l drops out) then has
  (k - 1) S^2 / sigma^2 ~ chi-square(k - 1), approximately (pairs far apart are nearly
  independent).

Both give a one-sided p-value for "the model is overconfident"; a small one is reported
with its evidence. The mean square of the z_i misses one run far from its prediction among
many close ones (|z| = 5.5 among twenty passed it in a trial study), so the largest |z_i|
is tested too, Bonferroni over the n runs: P(max |z| >= m) <= n erfc(m / sqrt 2).

A third check is of the cheap level's scale, with no p-value. Where the pairs show a
scale (``priors.shows_scale``: five or more pairs at correlation >= 0.9, whose slope
cuts the sd of their differences by 4), their least-squares slope measures rho_l, and a fitted rho_l more
than 2x away from it is reported. The fit centres the scale's prior on that slope, so
this is rare there; hyperparameters held fixed (``--fixed-hyperparameters``), or a fit in
which a discrepancy explained the pairs better, meet it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import solve_triangular
from scipy.stats import chi2

from bams_cli.core.gp._numerics import FloatArray, IntArray
from bams_cli.core.gp.hyperparameters import Hyperparameters
from bams_cli.core.gp.model import MFGP
from bams_cli.core.gp.priors import (
    pair_evidence,
    paired_differences,
    paired_values,
    shows_scale,
)

#: A check's p-value below this is reported as a warning.
CHECK_LEVEL = 0.01
#: At most this many level-0 points enter the leave-one-out check: each costs an O(n^2)
#: triangular solve, and 500 standardised residuals pin their mean square to ~+-0.13.
_MAX_LOO = 500


@dataclass
class PairCheck:
    """Paired level-0 / level-l differences against the fitted discrepancy.

    Attributes
    ----------
    level : int
    n_pairs : int
    sd_observed : float
        Sample sd of y_l - rho_l y_0 over the pairs (NaN below 2 pairs).
    sd_fitted : float
        rho_l sqrt(s_l + tau_l^2 + tau_0^2), the model's sd of the same difference.
    p_value : float
        P(chi-square(k - 1) >= (k - 1) S^2 / sd_fitted^2); small = overconfident.
    """

    level: int
    n_pairs: int
    sd_observed: float
    sd_fitted: float
    p_value: float


@dataclass
class ModelChecks:
    """Result of ``check_model``.

    Attributes
    ----------
    loo_n : int
        Level-0 observations in the leave-one-out check.
    loo_mean_z2 : float
        Mean squared standardised LOO residual (1 for a calibrated model; NaN if loo_n = 0).
    loo_max_abs_z : float
    loo_p_value : float
        P(chi-square(n) >= sum z^2).
    loo_max_p_value : float
        min(1, n erfc(max |z| / sqrt 2)): Bonferroni's bound on P(some |z_i| >= max |z|).
    loo_max_row : int
        Pool row of the level-0 run with the largest |z| (-1 when there is none).
    loo_of : int
        Level-0 observations the model holds (the check takes a random ``_MAX_LOO`` of
        them when there are more).
    pairs : list of PairCheck, one per level >= 1
    warnings : list of str
    """

    loo_n: int
    loo_mean_z2: float
    loo_max_abs_z: float
    loo_p_value: float
    loo_max_p_value: float = math.nan
    loo_max_row: int = -1
    loo_of: int = 0
    pairs: list[PairCheck] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN becomes None)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "loo_level0": {
                "n": self.loo_n,
                "mean_z2": num(self.loo_mean_z2),
                "max_abs_z": num(self.loo_max_abs_z),
                "p_value": num(self.loo_p_value),
                "max_p_value": num(self.loo_max_p_value),
                "of": max(self.loo_of, self.loo_n),
            },
            "pairs": [
                {
                    "level": p.level,
                    "n_pairs": p.n_pairs,
                    "sd_observed": num(p.sd_observed),
                    "sd_fitted": num(p.sd_fitted),
                    "p_value": num(p.p_value),
                }
                for p in self.pairs
            ],
        }


def fitted_discrepancy_sd(hp: Hyperparameters, level: int = 1) -> float:
    """The model's sd of y_l - rho_l y_0 at one segment: rho_l sqrt(s_l + tau_l^2 + tau_0^2).

    y_l - rho_l y_0 = b_l + rho_l (alpha_l(x) + eps_l - eps_0) under the model
    (``Hyperparameters.scales``); the offset b_l is a constant and does not count (module
    docstring). At rho_l = 1 (the additive model) this is the sd of y_l - y_0; for a
    scaled level it is the discrepancy left once the scale is taken out, in level l's
    units, which the pool's sd(f_l - rho_l f_0) measures.
    """
    rho = float(hp.scales[level - 1])  # type: ignore[index]
    return rho * math.sqrt(hp.outputscales[level - 1] + hp.noise[level] + hp.noise[0])


def loo_level0(model: MFGP, rng: np.random.Generator | None = None) -> FloatArray:
    """Standardised leave-one-out residuals z_i at (up to 500) level-0 observations.

    Returns
    -------
    z : ndarray of shape (k,)
        R&W eq. 5.12 in standardised form; a random subset of level-0 points when there
        are more than ``_MAX_LOO`` (``rng``, default seed 0).
    """
    return _loo_rows_and_z(model, rng)[1]


def _loo_rows_and_z(
    model: MFGP, rng: np.random.Generator | None = None
) -> tuple[IntArray, FloatArray]:
    """``loo_level0``'s residuals and the training rows they belong to."""
    rows = np.flatnonzero(model.levels_train == 0)
    if rows.size > _MAX_LOO:
        rng = np.random.default_rng(0) if rng is None else rng
        rows = np.sort(rng.choice(rows, _MAX_LOO, replace=False))
    if rows.size == 0:
        return rows, np.zeros(0)
    n = model.levels_train.size
    # [K^-1]_ii = || L^-1 e_i ||^2
    E = np.zeros((n, rows.size))
    E[rows, np.arange(rows.size)] = 1.0
    V = solve_triangular(model._L, E, lower=True, check_finite=False)
    kinv_diag = np.einsum("ij,ij->j", V, V)
    return rows, model._alpha[rows] / np.sqrt(kinv_diag)


def check_model(model: MFGP, seg: IntArray, names: Any = None) -> ModelChecks:
    """Leave-one-out and paired-difference checks of a fitted model (module docstring).

    Parameters
    ----------
    model : MFGP
    seg : int ndarray of shape (n_obs,)
        Segment of each training observation, to find pairs.
    names : sequence, optional
        Segment ids by pool row, to name the run farthest from its prediction.

    Returns
    -------
    ModelChecks
    """
    rows, z = _loo_rows_and_z(model)
    n = z.size
    s2 = float(np.sum(z * z))
    far = int(np.argmax(np.abs(z))) if n else -1
    m = float(abs(z[far])) if n else math.nan
    checks = ModelChecks(
        loo_n=n,
        loo_mean_z2=s2 / n if n else math.nan,
        loo_max_abs_z=m,
        loo_p_value=float(chi2.sf(s2, n)) if n else math.nan,
        loo_max_p_value=min(1.0, n * math.erfc(m / math.sqrt(2.0))) if n else math.nan,
        loo_max_row=int(seg[rows[far]]) if n else -1,
        loo_of=int(np.sum(model.levels_train == 0)),
    )
    if n >= 5 and checks.loo_p_value < CHECK_LEVEL:
        checks.warnings.append(
            f"the model is overconfident at level 0: its leave-one-out residuals at {n} "
            f"level-0 runs have mean square {checks.loo_mean_z2:.2f} (1 if calibrated; "
            f"largest |z| {checks.loo_max_abs_z:.1f}, p = {checks.loo_p_value:.1g}); its "
            "failure probabilities are too sure of themselves, so more level-0 runs help"
        )
    elif n >= 5 and checks.loo_max_p_value < CHECK_LEVEL:
        who = (
            f"segment {names[checks.loo_max_row]}"
            if names is not None
            else f"pool row {checks.loo_max_row}"
        )
        checks.warnings.append(
            f"the model is overconfident at level 0 near {who}: its level-0 result is "
            f"{m:.1f} sd from the model's leave-one-out prediction (the largest of {n} "
            f"level-0 runs, p = {checks.loo_max_p_value:.1g}, although their mean square "
            f"{checks.loo_mean_z2:.2f} passes); failure probabilities near it are too sure "
            "of themselves, so level-0 runs there help"
        )
    hp = model.hyperparameters
    for lv in range(1, model.n_levels):
        rho = float(hp.scales[lv - 1])  # type: ignore[index]
        d = paired_differences(seg, model.levels_train, model.y_train, lv, rho)
        k = d.size
        sd_fit = fitted_discrepancy_sd(hp, lv)
        sd_obs = float(np.std(d, ddof=1)) if k >= 2 else math.nan
        p = float(chi2.sf((k - 1) * sd_obs**2 / sd_fit**2, k - 1)) if k >= 2 else math.nan
        checks.pairs.append(PairCheck(lv, k, sd_obs, sd_fit, p))
        _, slope, corr, gain = pair_evidence(
            *paired_values(seg, model.levels_train, model.y_train, lv)
        )
        if shows_scale(k, slope, corr, gain) and max(slope / rho, rho / slope) > 2.0:
            checks.warnings.append(
                f"level {lv}'s values are {slope:.3g} times level 0's at the {k} segments run "
                f"at both (their least-squares slope), but the model's scale for it is "
                f"{rho:.3g} (held fixed, or a discrepancy explained the pairs better), so "
                "it trusts the level less than the pairs suggest"
            )
        if k >= 3 and p < CHECK_LEVEL:
            what = f"y{lv} - y0" if rho == 1.0 else f"y{lv} - {rho:.3g} y0"
            checks.warnings.append(
                f"level {lv} differs from level 0 more than the model allows: {k} segments "
                f"run at both give sd({what}) = {sd_obs:.3g} against the model's "
                f"{sd_fit:.3g} (p = {p:.1g}); the model trusts level {lv} too much"
            )
    return checks
