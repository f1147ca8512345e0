"""A suite of unlike problems with truth at both levels, to choose defaults on.

The tool's defaults were first tuned on ``toy2d`` and ``av_like`` (``core.synthetic``), whose
cheap level is nearly exact and whose failures sit in a few smooth dips. Real studies are
less kind; each problem here breaks one of those comforts (DESIGN.md, "Off the sample
data"). Two levels everywhere: column 0 of ``truth`` is the expensive level, column 1 the
cheap one.

==============  ====================================================================
problem         what makes it unlike toy2d / av_like
==============  ====================================================================
weak_cheap      cheap level weakly correlated (0.5-0.8) with a bias that depends on x,
                blind to one failure mode (>= 30 % of failures pass at level 1);
                7-d latent seen through a 32-d embedding; rate ~1.5 %
digits          real data (scikit-learn's bundled 8x8 digits, 1,797 images): f0 is the
                out-of-fold margin of the true label under an RBF SVM, failure =
                misclassified; the cheap level is a logistic regression on 5 PCA
                components; 64 pixel features; rate ~2 %
rare_regions    rate ~0.3 % in 5 small separated regions of a 24-d latent, seen
                through a 96-d embedding; cheap level informative but noisy and biased
gap_sim         a kinematic car-following simulator: f = minimum gap in metres, tens of
                metres far from failure, fractions of one at failure (gamma = 0.5 m);
                the cheap level (coarse time step, saturated braking) overestimates
                the gap under hard braking; 16-d embedding of 6 scenario parameters
==============  ====================================================================

Every generator is a pure function of ``n`` and ``seed``; gamma is fixed per problem (it
does not move with ``n``), so a small pool is a sample of the same problem as a large one.
The embedding maps depend on the seed alone, so pools of every size share them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from bams_cli.core.synthetic import SyntheticPool

FloatArray = NDArray[np.float64]

#: Problem name -> default pool size.
DEFAULT_N = {"weak_cheap": 20_000, "digits": 1_797, "rare_regions": 20_000, "gap_sim": 30_000}


def _embed(
    U: FloatArray,
    dim: int,
    hidden: int,
    noise: float,
    map_seed: list[int],
    rng: np.random.Generator,
) -> FloatArray:
    """A fixed random two-layer tanh map of the latent plus isotropic noise.

    Parameters
    ----------
    U : ndarray of shape (n, d)
        Latent (standardised).
    dim, hidden : int
        Embedding and hidden widths.
    noise : float
        Sd of the noise added to every embedding coordinate.
    map_seed : list of int
        Seeds the map alone, so it does not depend on n.
    rng : numpy.random.Generator
        Draws the noise.

    Returns
    -------
    ndarray of shape (n, dim)
    """
    map_rng = np.random.default_rng(map_seed)
    d = U.shape[1]
    A1 = map_rng.standard_normal((d, hidden)) / np.sqrt(d)
    A2 = map_rng.standard_normal((hidden, dim)) / np.sqrt(hidden)
    return np.tanh(U @ A1) @ A2 + noise * rng.standard_normal((U.shape[0], dim))


def _latent_problem(
    prefix: str,
    n: int,
    seed: int,
    stream: int,
    latent_dim: int,
    embed_dim: int,
    hidden: int,
    levels: Callable[[FloatArray, np.random.Generator], tuple[FloatArray, FloatArray]],
    gamma: float,
    cost: float,
) -> SyntheticPool:
    """A pool of n latent points u ~ N(0, I), seen through ``_embed``, with (f0, f1) =
    ``levels(u, rng)``; random streams [seed, stream] and [seed, stream + 1]."""
    rng = np.random.default_rng([seed, stream])
    U = rng.standard_normal((n, latent_dim))
    E = _embed(U, embed_dim, hidden, 0.05, [seed, stream + 1], rng)
    f0, f1 = levels(U, rng)
    return SyntheticPool(
        ids=[f"{prefix}-{i:06d}" for i in range(n)],
        features=E,
        truth=np.column_stack([f0, f1]),
        gamma=gamma,
        costs=[1.0, cost],
        extra={},
        latent=U,
    )


def _bump(U: FloatArray, center: FloatArray, dims: slice, width: float) -> FloatArray:
    r2 = ((U[:, dims] - center) ** 2).sum(axis=1)
    return np.exp(-r2 / (2 * width**2))


# ---------------------------------------------------------------------------------------
# weak_cheap
# ---------------------------------------------------------------------------------------
WEAK_LATENT_DIM = 7
WEAK_EMBED_DIM = 32
WEAK_GAMMA = 0.5
WEAK_COST = 0.15


def _weak_levels(U: FloatArray, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """(f0, f1) of weak_cheap at latent points U.

    Two failure modes: A (dims 0-1), which the cheap level sees, and B (dims 2-3), which it
    misses because its bias is large and positive exactly there. Away from B the bias drifts
    with u4 and u5, so no constant offset corrects it.
    """
    mode_a = _bump(U, np.array([1.7, 1.2]), slice(0, 2), 0.55)
    mode_b = _bump(U, np.array([-1.4, 1.6]), slice(2, 4), 0.55)
    f0 = 2.4 + 0.35 * np.sin(1.3 * U[:, 6]) + 0.25 * U[:, 5] - 2.2 * mode_a - 2.2 * mode_b
    bias = 0.45 * U[:, 4] - 0.25 * np.cos(1.5 * U[:, 5]) + 1.6 * mode_b
    f1 = f0 + bias + 0.3 * rng.standard_normal(U.shape[0])
    return f0, f1


def weak_cheap(n: int = DEFAULT_N["weak_cheap"], seed: int = 0) -> SyntheticPool:
    """A weak, biased cheap level that is blind to one of the two failure modes.

    Latent u ~ N(0, I_7); features = 32-d random tanh map of u + N(0, 0.05^2) noise.
    f0 = smooth drift minus two Gaussian dips (modes A and B); f1 = f0 + b(u) + N(0, 0.3^2)
    with b(u) = 0.45 u4 - 0.25 cos(1.5 u5) + 1.6 [mode B bump], so corr(f0, f1) is about
    0.6, the bias varies with u, and the failures of mode B (about 40 % of all) pass at the
    cheap level. gamma = 1.0 gives a rate of about 1.5 %; cheap level cost 0.15.

    Parameters
    ----------
    n : int
        Pool size.
    seed : int
        Seeds the latent, the map and the noise.

    Returns
    -------
    SyntheticPool
    """
    return _latent_problem(
        "wc", n, seed, 11, WEAK_LATENT_DIM, WEAK_EMBED_DIM, 48, _weak_levels, WEAK_GAMMA, WEAK_COST
    )


# ---------------------------------------------------------------------------------------
# digits
# ---------------------------------------------------------------------------------------
DIGITS_N = 1_797
DIGITS_GAMMA = 0.0
DIGITS_COST = 0.1
DIGITS_FOLDS = 5
DIGITS_TREES = 100
DIGITS_CHEAP_PCA = 8
DIGITS_CHEAP_NEIGHBOURS = 15


def label_margin(P: FloatArray, y: NDArray[np.int64]) -> FloatArray:
    """Probability of the true class minus the largest probability of any other class.

    Parameters
    ----------
    P : ndarray of shape (n, n_classes)
        Predicted class probabilities; column k is class k.
    y : int ndarray of shape (n,)
        True labels.

    Returns
    -------
    ndarray of shape (n,) in [-1, 1]
        > 0 exactly where the true class is strictly the most probable, so margin <= 0
        means misclassified (a tie counts as a miss: the model did not prefer the truth).
    """
    rows = np.arange(y.size)
    true = P[rows, y]
    others = P.copy()
    others[rows, y] = -np.inf
    return true - others.max(axis=1)


def digits_models(seed: int = 0) -> tuple[object, object, object]:
    """(expensive model, cheap model, folds) behind ``digits``, for checks that refit them.

    The expensive level is a random forest on the 64 pixels; the cheap one a 15-nearest-
    neighbour vote on 8 PCA components: a different family, so its errors are not a
    superset of the forest's and about a third of the forest's misses look fine to it.
    """
    from sklearn.decomposition import PCA
    from sklearn.ensemble import RandomForestClassifier
    from sklearn.model_selection import StratifiedKFold
    from sklearn.neighbors import KNeighborsClassifier
    from sklearn.pipeline import make_pipeline

    expensive = RandomForestClassifier(DIGITS_TREES, random_state=seed, n_jobs=1)
    cheap = make_pipeline(
        PCA(DIGITS_CHEAP_PCA, random_state=seed), KNeighborsClassifier(DIGITS_CHEAP_NEIGHBOURS)
    )
    folds = StratifiedKFold(DIGITS_FOLDS, shuffle=True, random_state=seed)
    return expensive, cheap, folds


@functools.lru_cache(maxsize=4)
def _digits_margins(seed: int) -> tuple[FloatArray, NDArray[np.int64], FloatArray, FloatArray]:
    """(pixels, labels, f0, f1) over all 1,797 images; cached, as the forest takes seconds."""
    from sklearn.datasets import load_digits
    from sklearn.model_selection import cross_val_predict

    data = load_digits()
    X = data.data.astype(np.float64)
    y = data.target.astype(np.int64)
    expensive, cheap, folds = digits_models(seed)
    f0 = label_margin(cross_val_predict(expensive, X, y, cv=folds, method="predict_proba"), y)
    f1 = label_margin(cross_val_predict(cheap, X, y, cv=folds, method="predict_proba"), y)
    return X, y, f0, f1


def digits(n: int = DIGITS_N, seed: int = 0) -> SyntheticPool:
    """Real data: misclassifications of scikit-learn's bundled 8x8 digits (1,797 images).

    f0 = out-of-fold ``label_margin`` of a random forest (100 trees), f1 = the same of a
    15-NN vote on 8 PCA components (cost 0.1); both from ``cross_val_predict`` over the
    same 5 stratified folds, so every segment's margin comes from a model that never saw
    it. Failure = f0 <= 0 (misclassified); rate about 2.5 %, corr(f0, f1) about 0.7,
    about a third of the failures have f1 > 0. Features = the 64 pixel values (0-16).
    The seed moves the folds, the forest and the PCA solver.

    Parameters
    ----------
    n : int
        Pool size, at most 1,797: a smaller pool is a seed-chosen subset of the images,
        with the margins of the full cross-validation (the problem does not change with n).
    seed : int

    Returns
    -------
    SyntheticPool
        ``extra["label"]``: the true digit.
    """
    if not 1 <= n <= DIGITS_N:
        raise ValueError(f"digits has {DIGITS_N} images; n = {n} is out of range")
    X, y, f0, f1 = (a.copy() for a in _digits_margins(seed))
    keep = np.arange(DIGITS_N)
    if n < DIGITS_N:
        keep = np.sort(np.random.default_rng([seed, 31]).choice(DIGITS_N, n, replace=False))
    return SyntheticPool(
        ids=[f"digit-{i:04d}" for i in keep],
        features=X[keep].astype(np.float64),
        truth=np.column_stack([f0[keep], f1[keep]]),
        gamma=DIGITS_GAMMA,
        costs=[1.0, DIGITS_COST],
        extra={"label": y[keep]},
    )


# ---------------------------------------------------------------------------------------
# rare_regions
# ---------------------------------------------------------------------------------------
RARE_LATENT_DIM = 24
RARE_EMBED_DIM = 96
RARE_REGIONS = 5
RARE_REGION_DIMS = 4
RARE_CENTER_NORM = 2.2
RARE_WIDTH = 0.45
RARE_CORE_DEPTH = 1.1
RARE_BASIN_RADIUS = 2.2
RARE_BASIN_DEPTH = 1.2
RARE_GAMMA = 0.45
RARE_COST = 0.15


def rare_region_centers() -> FloatArray:
    """Latent centres of the failure regions, shape (RARE_REGIONS, RARE_LATENT_DIM).

    Region k lives in its own block of 4 latent coordinates (4k .. 4k + 3) at distance
    2.2 from the origin, so any two centres are 2.2 sqrt(2) = 3.1 apart, about seven
    region widths. The last 4 coordinates carry no region, only a gentle drift.
    """
    C = np.zeros((RARE_REGIONS, RARE_LATENT_DIM))
    direction = np.array([1.0, -1.0, 1.0, 1.0]) / 2.0
    for k in range(RARE_REGIONS):
        sign = 1.0 if k % 2 == 0 else -1.0
        C[k, RARE_REGION_DIMS * k : RARE_REGION_DIMS * (k + 1)] = (
            sign * RARE_CENTER_NORM * np.roll(direction, k)
        )
    return C


def rare_region_of(U: FloatArray) -> tuple[NDArray[np.int64], FloatArray]:
    """The region each latent point is closest to, measured inside the region's own block.

    Parameters
    ----------
    U : ndarray of shape (n, RARE_LATENT_DIM)

    Returns
    -------
    region : int ndarray of shape (n,)
    distance : ndarray of shape (n,)
        Euclidean distance to that region's centre within its 4 coordinates.
    """
    C = rare_region_centers()
    D = np.column_stack(
        [
            np.linalg.norm(U[:, RARE_REGION_DIMS * k : RARE_REGION_DIMS * (k + 1)]
                           - C[k, RARE_REGION_DIMS * k : RARE_REGION_DIMS * (k + 1)], axis=1)
            for k in range(RARE_REGIONS)
        ]
    )  # fmt: skip
    region = D.argmin(axis=1)
    return region, D[np.arange(U.shape[0]), region]


def _rare_levels(U: FloatArray, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """(f0, f1) of rare_regions at latent points U."""
    C = rare_region_centers()
    # A bounded drift (>= 1.4): no failure can arise from the drift alone, far from a region.
    f0 = 2.0 + 0.3 * np.sin(U[:, 20]) + 0.2 * np.tanh(U[:, 21]) + 0.1 * np.tanh(U[:, 22] * U[:, 23])
    bias = 0.25 * np.tanh(U[:, 22]) + 0.1 * U[:, 0]
    for k in range(RARE_REGIONS):
        dims = slice(RARE_REGION_DIMS * k, RARE_REGION_DIMS * (k + 1))
        bump = _bump(U, C[k, dims], dims, RARE_WIDTH)
        # A basin that slopes toward the region from RARE_BASIN_RADIUS away, with a narrow
        # core at its bottom where the failures are: rare failures at the end of a trend a
        # model can follow, as in real data, not needles no sampler could find.
        dist = np.linalg.norm(U[:, dims] - C[k, dims], axis=1)
        basin = np.maximum(0.0, 1.0 - dist / RARE_BASIN_RADIUS) ** 2
        f0 = f0 - RARE_BASIN_DEPTH * basin - RARE_CORE_DEPTH * bump
        # The cheap level sees every region, but at a different depth in each: it
        # overstates some (false alarms) and understates others (missed failures).
        bias = bias + 0.5 * (k % 3 - 1) * bump
    f1 = f0 + bias + 0.2 * rng.standard_normal(U.shape[0])
    return f0, f1


def rare_regions(n: int = DEFAULT_N["rare_regions"], seed: int = 0) -> SyntheticPool:
    """Rare failures (about 0.4 %) in 5 small separated regions of a 24-d latent.

    Latent u ~ N(0, I_24); features = 96-d random tanh map of u + N(0, 0.05^2).
    f0 = smooth drift minus, around each of the ``rare_region_centers``, a basin sloping
    down over a radius of 2.2 and a narrow Gaussian core (width 0.45) at its bottom;
    every failure lies in a core; f1 = f0 + a bias that varies with u and from region to region
    + N(0, 0.2^2); corr(f0, f1) about 0.8. gamma = 0.5; cheap level cost 0.15.

    Parameters
    ----------
    n : int
        Pool size.
    seed : int

    Returns
    -------
    SyntheticPool
        ``latent`` holds u; ``rare_region_of`` says which region a point is in.
    """
    return _latent_problem(
        "rr", n, seed, 41, RARE_LATENT_DIM, RARE_EMBED_DIM, 128, _rare_levels, RARE_GAMMA, RARE_COST
    )


# ---------------------------------------------------------------------------------------
# gap_sim
# ---------------------------------------------------------------------------------------
GAP_GAMMA = 0.5
GAP_COST = 0.2
GAP_EMBED_DIM = 16
GAP_FINE_DT = 0.02
GAP_COARSE_DT = 0.25
GAP_HORIZON = 10.0
#: Scenario parameters (the latent), in this column order.
GAP_PARAMETERS = (
    "ego_speed",  # m/s
    "lead_speed",  # m/s
    "initial_gap",  # m
    "lead_decel",  # m/s^2, the lead's braking
    "reaction_time",  # s, until the ego starts braking
    "ego_decel",  # m/s^2, the ego's braking
)
#: Lead braking above this (m/s^2) is "hard": the coarse simulator's tyre model saturates.
GAP_HARD_BRAKING = 6.0


def min_gap(S: FloatArray, *, dt: float, reaction_time: FloatArray | None = None) -> FloatArray:
    """Minimum signed gap (m) over a lead-vehicle braking event, stepped every ``dt`` s.

    At t = 0 the lead brakes to a stop at ``lead_decel``; the ego keeps its speed until
    ``reaction_time`` and then brakes to a stop at ``ego_decel``. Within a step each car
    moves exactly under constant deceleration (and stops when its speed reaches 0); the
    gap is read at the end of every step over ``GAP_HORIZON`` s, which covers the ego's
    slowest stop. A collision ends the run at gap 0, as a simulator with contact does, so
    the metric has a floor: every collision scores 0, however violent.

    Parameters
    ----------
    S : ndarray of shape (n, 6)
        Scenario parameters in ``GAP_PARAMETERS`` order.
    dt : float
        Step, s.
    reaction_time : ndarray of shape (n,), optional
        Overrides column 4 (the coarse simulator rounds it to its tick).

    Returns
    -------
    ndarray of shape (n,)
    """
    v_e, v_l, d0, b_l, t_r, b_e = (S[:, j].copy() for j in range(6))
    if reaction_time is not None:
        t_r = reaction_time
    x_l, x_e = d0.copy(), np.zeros_like(d0)
    gap = d0.copy()
    for k in range(int(round(GAP_HORIZON / dt))):
        t = k * dt
        # Time each car still decelerates within this step (0 once stopped).
        tau_l = np.minimum(dt, v_l / b_l)
        braking = t >= t_r - 1e-12
        tau_e = np.where(braking, np.minimum(dt, v_e / b_e), 0.0)
        x_l += v_l * tau_l - 0.5 * b_l * tau_l**2
        x_e += v_e * (dt - tau_e) * (~braking) + (v_e * tau_e - 0.5 * b_e * tau_e**2)
        v_l = v_l - b_l * tau_l
        v_e = np.where(braking, v_e - b_e * tau_e, v_e)
        np.minimum(gap, x_l - x_e, out=gap)
    # The simulator stops at contact: a collision is a gap of 0, however fast.
    return np.maximum(gap, 0.0)


def gap_scenarios(n: int, rng: np.random.Generator) -> FloatArray:
    """Draw n scenarios (rows in ``GAP_PARAMETERS`` order), shape (n, 6).

    Ego speed U(8, 30) m/s; lead speed = ego + N(0, 2.5^2), >= 0; initial gap = time
    headway x ego speed with headway log-normal (median 2.9 s, sd of log 0.3); lead
    braking U(1, 9) m/s^2; reaction U(0.3, 1.5) s; ego braking U(5, 9) m/s^2.
    """
    v_e = rng.uniform(8.0, 30.0, n)
    v_l = np.maximum(v_e + 2.5 * rng.standard_normal(n), 0.0)
    headway = np.exp(np.log(2.9) + 0.3 * rng.standard_normal(n))
    b_l = rng.uniform(1.0, 9.0, n)
    t_r = rng.uniform(0.3, 1.5, n)
    b_e = rng.uniform(5.0, 9.0, n)
    return np.column_stack([v_e, v_l, headway * v_e, b_l, t_r, b_e])


def coarse_min_gap(S: FloatArray) -> FloatArray:
    """The cheap simulator: 0.25 s ticks and a tyre model that saturates under hard braking.

    It rounds the reaction time to its tick (unbiased on average) and reads the gap only
    at ticks (misses minima between them, small), and above ``GAP_HARD_BRAKING`` it
    credits the lead with only 70 % of the extra deceleration, so it overestimates the
    gap exactly where the lead brakes hard: where the system is stressed.
    """
    S = S.copy()
    b = S[:, 3]
    S[:, 3] = np.where(b > GAP_HARD_BRAKING, GAP_HARD_BRAKING + 0.7 * (b - GAP_HARD_BRAKING), b)
    t_r = np.round(S[:, 4] / GAP_COARSE_DT) * GAP_COARSE_DT
    return min_gap(S, dt=GAP_COARSE_DT, reaction_time=t_r)


def gap_sim(n: int = DEFAULT_N["gap_sim"], seed: int = 0) -> SyntheticPool:
    """A car-following simulator: f = minimum gap (m) when the lead vehicle brakes.

    f0 = ``min_gap`` at 0.02 s steps, f1 = ``coarse_min_gap`` (cost 0.2). gamma = 0.5 m,
    a near collision; the rate is about 0.7 %. Far from failure the gap varies by tens of
    metres (sd about 27 m among non-failures), at failure by fractions of one: about 93 %
    of the failures are collisions, which the simulator scores 0 (contact). The cheap
    simulator misses about 20 % of the failures, those under hard lead braking.
    Features = a 16-d random tanh map of the standardised scenario + N(0, 0.05^2) noise.

    Parameters
    ----------
    n : int
        Pool size.
    seed : int

    Returns
    -------
    SyntheticPool
        ``latent`` = the scenario parameters (``GAP_PARAMETERS``); ``extra["difficulty"]``
        = minus the time headway (s) with noise, the kind of triage score a team already
        has (tight following is riskier), for the DS strategies.
    """
    rng = np.random.default_rng([seed, 51])
    S = gap_scenarios(n, rng)
    # Standardise with the scenario distribution's own constants, not the pool's, so the
    # map does not move with n.
    loc = np.array([19.0, 19.0, 57.0, 5.0, 0.9, 7.0])
    scale = np.array([6.4, 6.9, 26.0, 2.3, 0.35, 1.15])
    E = _embed((S - loc) / scale, GAP_EMBED_DIM, 32, 0.05, [seed, 52], rng)
    f0 = min_gap(S, dt=GAP_FINE_DT)
    f1 = coarse_min_gap(S)
    difficulty = -S[:, 2] / S[:, 0] + 0.3 * rng.standard_normal(n)
    return SyntheticPool(
        ids=[f"gap-{i:06d}" for i in range(n)],
        features=E,
        truth=np.column_stack([f0, f1]),
        gamma=GAP_GAMMA,
        costs=[1.0, GAP_COST],
        extra={"difficulty": difficulty},
        latent=S,
    )
