"""Synthetic stand-ins for sample data. Not real fleet data.

- ``toy2d``: the paper's synthetic problem (appendix "Synthetic Experiments").
- ``av_like``: a stand-in for the paper's AV setting (section 4): 512-d embeddings made from
  a 12-d latent by a fixed nonlinear map plus noise, 32 stochastic rollouts per segment
  each giving a minimum time-to-collision (TTC); f = 25th percentile of the 32.

Everything is a pure function of ``n`` and a seed, so the committed files can be regenerated
bit for bit and larger pools made on demand.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

TOY2D_GAMMA = 0.56
TOY2D_CENTER = 1.95
TOY2D_LEVEL1_NOISE = 0.1
TOY2D_LEVEL1_COST = 0.10

AV_LATENT_DIM = 12
AV_EMBED_DIM = 512
AV_ROLLOUTS = 32
AV_CHEAP_ROLLOUTS = 5
AV_RATE = 0.01


@dataclass
class SyntheticPool:
    """A synthetic pool with ground truth at every fidelity level.

    Attributes
    ----------
    ids : list of str, length n
    features : ndarray of shape (n, D)   what a user would hand to embed-reduce
    truth : ndarray of shape (n, L + 1)  metric f at each level (column 0 = high fidelity)
    gamma : float
    costs : list of float, length L + 1
    extra : dict of name -> ndarray of shape (n,)  pass-through columns
    latent : ndarray of shape (n, d) or None
        The hidden scenario behind ``features`` (suite problems; for tests, never written).
    """

    ids: list[str]
    features: NDArray[np.float64]
    truth: NDArray[np.float64]
    gamma: float
    costs: list[float]
    extra: dict[str, NDArray]
    latent: NDArray[np.float64] | None = field(default=None, repr=False)


def toy2d_f(X: NDArray[np.float64], c: float = TOY2D_CENTER) -> NDArray[np.float64]:
    """f(x) = ||(|x0| - c, x1 - c)||_1: two diamonds centred at (+-c, c) (appendix C)."""
    return np.abs(np.abs(X[:, 0]) - c) + np.abs(X[:, 1] - c)


def toy2d(n: int = 20_000, seed: int = 0) -> SyntheticPool:
    """The paper's two-diamond problem: x ~ N(0, I_2), level 1 = f + N(0, 0.1^2) at cost 0.1."""
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, 2))
    f0 = toy2d_f(X)
    f1 = f0 + TOY2D_LEVEL1_NOISE * rng.standard_normal(n)
    return SyntheticPool(
        ids=[f"t{i:06d}" for i in range(n)],
        features=X,
        truth=np.column_stack([f0, f1]),
        gamma=TOY2D_GAMMA,
        costs=[1.0, TOY2D_LEVEL1_COST],
        extra={},
    )


def _av_base_ttc(U: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mean minimum-TTC (seconds) as a smooth function of the latent scenario.

    Three failure modes (dense intersections, cut-ins, occluded pedestrians, say) are dips
    of the TTC surface in different latent directions; elsewhere TTC drifts gently.
    """
    modes = [
        (np.array([1.6, 1.2, 0.0]), slice(0, 3), 2.6, 0.9),
        (np.array([-1.5, 1.4, -0.8]), slice(3, 6), 2.4, 0.8),
        (np.array([1.3, -1.7]), slice(6, 8), 2.2, 0.7),
    ]
    ttc = 3.2 + 0.25 * np.sin(U[:, 8]) + 0.15 * U[:, 9]
    for center, dims, depth, width in modes:
        r2 = ((U[:, dims] - center) ** 2).sum(axis=1)
        ttc = ttc - depth * np.exp(-r2 / (2 * width**2))
    return ttc


def av_like(n: int = 2_000, seed: int = 0) -> SyntheticPool:
    """AV-like pool: 512-d embeddings, 32 rollouts, f = 25th percentile of min-TTC.

    The embedding map (two random layers with tanh) is fixed by ``seed`` alone, not by
    ``n``, so pools of every size share it and the first rows agree across sizes.
    """
    map_rng = np.random.default_rng([seed, 1])
    A1 = map_rng.standard_normal((AV_LATENT_DIM, 64)) / np.sqrt(AV_LATENT_DIM)
    A2 = map_rng.standard_normal((64, AV_EMBED_DIM)) / np.sqrt(64)

    rng = np.random.default_rng([seed, 2])
    U = rng.standard_normal((n, AV_LATENT_DIM))
    E = np.tanh(U @ A1) @ A2 + 0.05 * rng.standard_normal((n, AV_EMBED_DIM))

    base = _av_base_ttc(U)
    # Rollout spread grows where the scenario is tight: interactive agents disagree more.
    spread = 0.25 + 0.15 * np.exp(-np.maximum(base, 0))
    rollouts = np.maximum(
        base[:, None] + spread[:, None] * rng.standard_normal((n, AV_ROLLOUTS)), 0.0
    )
    f0 = np.quantile(rollouts, 0.25, axis=1)
    f1 = np.quantile(rollouts[:, :AV_CHEAP_ROLLOUTS], 0.25, axis=1)
    # gamma from a large reference pool, so it does not move with n.
    gamma = _av_gamma(seed)
    difficulty = -f0 + 0.6 * rng.standard_normal(n)
    return SyntheticPool(
        ids=[f"seg-{i:06d}" for i in range(n)],
        features=E,
        truth=np.column_stack([f0, f1]),
        gamma=gamma,
        costs=[1.0, AV_CHEAP_ROLLOUTS / AV_ROLLOUTS],
        extra={"difficulty": difficulty},
    )


def _av_gamma(seed: int, n_ref: int = 200_000) -> float:
    """The AV_RATE quantile of f over a reference pool of n_ref latent draws."""
    rng = np.random.default_rng([seed, 3])
    U = rng.standard_normal((n_ref, AV_LATENT_DIM))
    base = _av_base_ttc(U)
    spread = 0.25 + 0.15 * np.exp(-np.maximum(base, 0))
    rollouts = np.maximum(
        base[:, None] + spread[:, None] * rng.standard_normal((n_ref, AV_ROLLOUTS)), 0.0
    )
    f0 = np.quantile(rollouts, 0.25, axis=1)
    return float(np.round(np.quantile(f0, AV_RATE), 4))
