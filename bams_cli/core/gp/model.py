"""The multifidelity GP conditioned on observations: the posterior BAMS needs."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_solve, solve_triangular
from scipy.special import ndtr
from threadpoolctl import threadpool_limits

from bams_cli import defaults
from bams_cli.core.gp._numerics import (
    LOG_2PI,
    FloatArray,
    GPFitError,
    IntArray,
    check_data,
    check_levels,
    cholesky_inplace,
)
from bams_cli.core.gp.hyperparameters import Hyperparameters, _pack
from bams_cli.core.gp.priors import PriorSpec, _Priors, level0_standardise, with_pair_modes
from bams_cli.core.kernels import (
    matern52,
    matern52_aug_lower,
    matern52_cross,
    matern52_cross_minus,
)

_REUSE_MIN_COLUMNS = 1024  # _obs_factor_reused: smaller sets are cheap to recompute
_THREADED_FROM = 2000  # MFGP(): factorise with every BLAS thread from this many observations
_CHUNK_ELEMENTS = 1 << 24  # score(): at most this many (chunk x n_obs) kernel entries
_OWN_BLOCK_ELEMENTS = 8 << 20  # own_point: n_obs x columns per block (64 MB)
_BOUND_MIN_OBS = 500  # _score_bounded: the bound's model conditions on at least this many
_BOUND_SHARE = 0.125  # _score_bounded: the bound's share of max_work; the rest refines


class _FactorCache:
    """Whitened factors L^-1 k_aug(Y_n, (x, l)) of a fixed point set, solved once each.

    Selection asks for the same few thousand points' factors again and again (a cluster's
    rows at every block of its covariance, its candidates at every pick and every exact
    evaluation); with thousands of observations each solve is n^2 per column, and at
    12,000 segments and 3,700 observations those repeats were 0.8 of select's time. With
    30 observations the kernel evaluations it saves were a third of the approximate plan's.
    Points are found by their centred coordinates, exactly (a hash of their bits, then
    compared); a point outside the set is solved as usual. Level 0's factor is theta0's
    (k_aug((x_n, l_n), (x, 0)) = k0). Each level's n x m array is allocated on first use
    and filled column by column.
    """

    def __init__(self, A: FloatArray, n: int, n_levels: int) -> None:
        self.A = np.ascontiguousarray(A)
        keys = _row_hash(self.A)
        self.order = np.argsort(keys, kind="stable")
        self.keys = keys[self.order]
        self.U: list[FloatArray | None] = [None] * n_levels
        self.have = np.zeros((n_levels, len(A)), dtype=bool)
        self.n = n

    def find(self, A: FloatArray) -> IntArray:
        """Index of each row of A in the set, -1 where it is not (or its hash is shared
        with another row of the set: it is then solved, which is merely slower)."""
        if len(self.keys) == 0 or len(A) == 0:
            return np.full(len(A), -1, dtype=np.int64)
        h = _row_hash(A)
        pos = np.minimum(np.searchsorted(self.keys, h), len(self.keys) - 1)
        at = self.order[pos]
        ok = (self.keys[pos] == h) & np.all(self.A[at] == A, axis=1)
        return np.where(ok, at, -1).astype(np.int64)


_HASH_MULTIPLIERS = np.random.default_rng(0x5EED).integers(1, 2**62, 4096, dtype=np.uint64) | 1


def _row_hash(A: FloatArray) -> NDArray[np.uint64]:
    """A 64-bit hash of each row's bits: their words times odd constants, summed mod 2^64."""
    A = np.ascontiguousarray(A, dtype=np.float64)
    W = A.view(np.uint64).reshape(A.shape)
    mult = np.resize(_HASH_MULTIPLIERS, A.shape[1])
    return (W * mult).sum(axis=1, dtype=np.uint64)


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
    priors : PriorSpec, optional
        The priors ``log_posterior`` is scored under (``with_pair_modes``).
    standardisation : (float, float), optional
        The (mean, std) those priors' units are: the fit's over every observation, when
        these data are a subset of them; default ``level0_standardise`` of these data.

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
    notes : list of str
        What a user should hear about this fit (jitter needed, constant data), one line each.
    X_train, levels_train, y_train : ndarray
        The observations conditioned on.
    """

    #: ``localised``'s factors of a fixed point set; None: every factor is solved.
    _local: _FactorCache | None = None
    #: ``_obs_factor_reused``'s one remembered (key, factor).
    _obs_factor_cache: tuple[bytes, FloatArray] | None = None

    def __init__(
        self,
        X: FloatArray,
        levels: IntArray,
        y: FloatArray,
        n_levels: int,
        hyperparameters: Hyperparameters,
        *,
        priors: PriorSpec | None = None,
        standardisation: tuple[float, float] | None = None,
    ) -> None:
        X, levels, y = check_data(X, levels, y, n_levels)
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
        # K is built and factorised in place, one n x n array at its peak (the budget of
        # exact conditioning, fit.BYTES_PER_ENTRY, rests on it); zeros, so the strict
        # upper triangle the kernel does not write is defined.
        K = np.zeros((n, n), order="F")

        def build() -> None:
            with np.errstate(over="ignore", invalid="ignore"):  # reported by the factoriser
                matern52_aug_lower(self._Xt, levels, self._ell, self._s, K)
            K[np.diag_indices(n)] += hp.noise[levels]

        build()
        mean_diag = float(np.mean(np.diag(K)))
        # One BLAS thread for small matrices (see fit_mfgp); all of them from a few
        # thousand observations on, where the factorisation is seconds of dense work.
        with threadpool_limits(limits=1 if n < _THREADED_FROM else None, user_api="blas"):
            self._L, self.jitter = cholesky_inplace(K, build)
        #: Facts about this fit a user should hear: jitter needed, a flat model.
        self.notes: list[str] = []
        #: How many observations the hyperparameter search saw (``fit.fit_subset``); all
        #: of them unless set by ``fit_mfgp``.
        self.fitted_on: int = int(np.asarray(y).size)
        #: Which observations the posterior conditions on (``fit.condition``): rows of the
        #: data it was given, None for all of them (this object's X_train is the rest).
        self.conditioned_rows: IntArray | None = None
        #: How it conditions: method "exact" (on all) or "exact_subset", conditioned_on,
        #: observations, memory_budget_bytes (``fit.condition`` fills it in).
        self.conditioning: dict[str, Any] = {
            "method": "exact",
            "conditioned_on": int(n),
            "observations": int(n),
            "memory_budget_bytes": None,
        }
        if self.jitter > 0.0:
            rel = self.jitter / mean_diag
            self.notes.append(
                f"the training covariance needed jitter {self.jitter:.3g} ({rel:.0e} of its "
                "mean diagonal) to factorise: some observations nearly repeat each other "
                "with almost no noise; predictions near them are slightly smoothed"
            )
        # A level-l value is rho_l (theta0 + delta_l + eps_l) + b_l (Hyperparameters):
        # (y - b_l) / rho_l is the additive model's observation, and y's density is its
        # density over prod rho_l (the Jacobian).
        offsets = np.concatenate([[0.0], hp.offsets])  # type: ignore[arg-type]
        rho = np.concatenate([[1.0], hp.scales])  # type: ignore[arg-type]
        r = (y - offsets[levels]) / rho[levels] - hp.mean
        self._alpha = cho_solve((self._L, True), r, check_finite=False)  # GPML Alg. 2.1 l. 3
        self.log_marginal_likelihood = float(
            -0.5 * r @ self._alpha
            - np.sum(np.log(np.diag(self._L)))
            - 0.5 * n * LOG_2PI
            - np.sum(np.log(rho[levels]))
        )  # GPML Alg. 2.1 line 7, with the Jacobian

        # The units the priors are scored in: the fit's, on every observation, when this
        # model conditions on a subset of them (``fit.condition``), else these data's.
        ybar, ystd = standardisation or level0_standardise(X, levels, y, n_levels)
        v = ystd**2
        theta_std = _pack(
            Hyperparameters(
                mean=0.0,
                outputscale0=hp.outputscale0 / v,
                lengthscales0=hp.lengthscales0,
                outputscales=hp.outputscales / v,
                lengthscales=hp.lengthscales,
                noise=hp.noise / v,
                scales=hp.scales,
            )
        )
        #: The priors ``log_posterior`` is scored under, discrepancy modes resolved
        #: (``fit`` resolves them on every observation; else from this model's own).
        self.priors = with_pair_modes(priors, X, levels, (y - ybar) / ystd, n_levels)
        if np.all(np.isfinite(theta_std)):
            lp, _ = _Priors.for_data(X, n_levels, self.priors).log_prior(theta_std)
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
        return check_levels(levels, self.n_levels, n, name)

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
        """W = L^-1 k_aug(Y_n, (Xc, lc)), shape (n, m), for centred Xc (a new array)."""
        cache = self._local
        if cache is None:
            return self._solve_L(self._k_aug(self._Xt, self.levels_train, Xc, lc))
        where = cache.find(Xc)
        W = np.empty((cache.n, len(Xc)), order="F")
        miss = np.flatnonzero(where < 0)
        if miss.size:
            W[:, miss] = self._solve_L(self._k_aug(self._Xt, self.levels_train, Xc[miss], lc[miss]))
        for lv in np.unique(lc[where >= 0]):
            cols = np.flatnonzero((lc == lv) & (where >= 0))
            at = where[cols]
            U = cache.U[lv]
            if U is None:
                U = cache.U[lv] = np.empty((cache.n, len(cache.A)), order="F")
            new = np.unique(at[~cache.have[lv, at]])
            if new.size:
                U[:, new] = self._solve_L(
                    self._k_aug(self._Xt, self.levels_train, cache.A[new], np.full(new.size, lv))
                )
                cache.have[lv, new] = True
            W[:, cols] = U[:, at]
        return W

    def _theta0_factor(self, A: FloatArray) -> FloatArray:
        """V = L^-1 k0(X_n, A), shape (n, m), for centred A: level 0's factor."""
        return self._obs_factor(A, np.zeros(len(A), dtype=np.int64))

    def nearest(self, X: FloatArray, k: int) -> MFGP:
        """This GP conditioned on the k observations nearest the points X, in level 0's
        lengthscales (the distance to the closest point of X, or of every j-th point of
        X past ``_NEAREST_POINTS``); ``self`` when k >= n.

        A local model for a region of the pool (a cluster, in ``select``): a far
        observation's covariance with the region decays with the Matern kernel, so leaving
        it out changes the posterior there little, and every factor costs k^2 per point
        instead of n^2. Conditioning on fewer jointly Gaussian observations never lowers a
        variance, and the local model carries the same noise, jitter included (as the
        bound of ``_score_bounded``): its sds are upper bounds of this model's.
        """
        from sklearn.neighbors import NearestNeighbors

        n = self._Xt.shape[0]
        if k >= n:
            return self
        ell = self._ell[0]
        X = np.asarray(X, dtype=np.float64)
        # Every ceil(m / _NEAREST_POINTS)-th point stands for the region (the distances of
        # 14,654 observations to a 25,000-point cluster took 24 s by k-d tree under load,
        # 5.4 s by brute force; 40 clusters of a million segments wait on it).
        X = X[:: max(1, -(-len(X) // _NEAREST_POINTS))]
        reach = NearestNeighbors(n_neighbors=1, algorithm="brute").fit(X / ell)
        dist = reach.kneighbors(self.X_train / ell, return_distance=True)[0][:, 0]
        return self._on_rows(np.sort(np.argsort(dist, kind="stable")[:k]))

    def _on_rows(self, rows: NDArray[np.intp]) -> MFGP:
        """This GP's hyperparameters conditioned on the observations ``rows`` only, with
        this model's jitter added to the noise: every variance it gives is at least this
        model's (fewer observations, no less noise), so its sds are upper bounds."""
        hp = self.hyperparameters
        return MFGP(
            self.X_train[rows], self.levels_train[rows], self.y_train[rows], self.n_levels,
            dataclasses.replace(hp, noise=hp.noise + self.jitter), priors=self.priors,
        )  # fmt: skip

    def localised(self, X: FloatArray, max_bytes: int) -> MFGP:
        """This posterior, solving the factors of the points X once and remembering them.

        Answers are those of ``self`` up to rounding (a factor solved with other columns
        beside it). Returns ``self`` when the factors of every level would exceed
        ``max_bytes`` (n x len(X) x n_levels floats). Worth it at any number of
        observations: with 30, the kernel evaluations it saves were 29% of the approximate
        plan's CPU at 45,000 segments. The copy shares every array with ``self``.
        """
        n = self._Xt.shape[0]
        if 8 * n * len(X) * self.n_levels > max_bytes:
            return self
        view = copy.copy(self)
        view._obs_factor_cache = None
        view._local = _FactorCache(self._centre(X), n, self.n_levels)
        return view

    def _obs_factor_reused(self, Xc: FloatArray, lc: IntArray) -> FloatArray:
        """``_obs_factor`` remembered for the last large candidate set (read-only result).

        Selection asks for one row of cov_obs_obs against all of a cluster's candidates
        at every pick (15,000 at N = 45k): the n x m factor is the same every time. One
        entry, keyed on the contents, so a changed set is simply recomputed.
        """
        if Xc.shape[0] < _REUSE_MIN_COLUMNS:
            return self._obs_factor(Xc, lc)
        key = hashlib.blake2b(Xc.tobytes() + lc.tobytes(), digest_size=16).digest()
        cached = self._obs_factor_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        W = self._obs_factor(Xc, lc)
        W.flags.writeable = False
        self._obs_factor_cache = (key, W)
        return W

    def _predict_block(self, Xc: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and (unclipped) variance of theta0 at centred rows Xc.

        Paper sec. 2 (GP predictions) with the constant mean; GPML Alg. 2.1.
        """
        mu, k = self._mean_block(Xc)
        v = self._solve_L(k.T)  # F-ordered view: LAPACK solves in place, no copy
        sigma2 = self._s[0] - np.einsum("ij,ij->j", v, v)  # GPML Alg. 2.1 lines 5-6
        return mu, sigma2

    def _mean_block(self, Xc: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean of theta0 at centred rows Xc, and k0(Xc, X_n) of shape (m, n)."""
        k = matern52_cross(Xc, self._Xt, self._ell[0], self._s[0])  # (m, n), C order
        return self.hyperparameters.mean + k @ self._alpha, k  # GPML Alg. 2.1 line 4

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
        Va = self._theta0_factor(A)
        Vb = self._theta0_factor(B)
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
        W = self._obs_factor(B, lc)
        if self._local is None and 2 * B.shape[0] < A.shape[0]:
            # Many rows, few columns (J after a batch over the whole pool): the data term
            # as k0(x, X_n) (K^-1 k_aug(Y_n, c)), n^2 per column, instead of a solve of
            # n^2 per row. At 45,000 segments and 3,700 observations, 18 s -> about 2 s.
            return self._cov_solved(A, B, self._solve_data_term(W))
        P = np.ascontiguousarray(self._theta0_factor(A).T @ W)
        return self._k0_minus(A, B, P)

    def cov_theta0_obs_to(
        self, Xc: FloatArray, levels: IntArray
    ) -> Callable[[FloatArray], FloatArray] | None:
        """X -> ``cov_theta0_obs(X, Xc, levels)`` with the columns' data term
        K^-1 k_aug(Y_n, c) solved once (n^2 per column), for a caller asking block after
        block of pool rows about the same columns (``core.select._Given``: J given
        thousands of pending picks, where each block solved them again). Each block then
        costs n per row and column, and the solve saves n^2 per row of every block after
        it, whatever the number of columns. None for a localised view, which caches its
        own factors."""
        B = self._centre(Xc, "Xc")
        if self._local is not None:
            return None
        Z = self._solve_data_term(self._obs_factor(B, self._levels(levels, B.shape[0])))
        return lambda X: self._cov_solved(self._centre(X), B, Z)

    def cov_obs_obs_from(
        self, Xa: FloatArray, levels_a: IntArray
    ) -> Callable[[FloatArray, IntArray], FloatArray] | None:
        """(Xb, levels_b) -> ``cov_obs_obs(Xa, levels_a, Xb, levels_b)`` for observations b
        none of which is one of a's (no noise term), with a's data term
        K^-1 k_aug(Y_n, a) solved once: pairs already in a batch against block after block
        of candidates (``core.select._Given.w_obs``), n per pair and candidate instead of
        n^2 per candidate. At level 0 these are cov_n(theta0(x_a), y_b) (theta0 is
        noise-free): the candidate screen's rows. None for a localised view."""
        if self._local is not None:
            return None
        A = self._centre(Xa, "Xa")
        la = self._levels(levels_a, A.shape[0], "levels_a")
        Z = self._solve_data_term(self._obs_factor(A, la))

        def cov(Xb: FloatArray, levels_b: IntArray) -> FloatArray:
            B = self._centre(Xb, "Xb")
            lb = self._levels(levels_b, B.shape[0], "levels_b")
            kb = self._k_aug(self._Xt, self.levels_train, B, lb)
            return self._k_aug(A, la, B, lb) - Z.T @ kb

        return cov

    def _solve_data_term(self, W: FloatArray) -> FloatArray:
        """K^-1 k_aug(Y_n, c) = L^-T W from the columns' factor W = L^-1 k_aug(Y_n, c)."""
        return solve_triangular(
            self._L, W, lower=True, trans="T", overwrite_b=True, check_finite=False
        )

    def _cov_solved(self, A: FloatArray, B: FloatArray, Z: FloatArray) -> FloatArray:
        """cov_n(theta0(A), y_B) = k0(A, B) - k0(A, X_n) Z for centred A, B and the
        columns' solved data term Z."""
        P = np.ascontiguousarray(matern52_cross(A, self._Xt, self._ell[0], self._s[0]) @ Z)
        return self._k0_minus(A, B, P)

    def _k0_minus(self, A: FloatArray, B: FloatArray, P: FloatArray) -> FloatArray:
        """k0(A, B) - P for centred A and B, in place of P."""
        # k0 depends on the coordinates only, and selection lists a point once per level in
        # consecutive columns: evaluate it once per run of identical rows.
        new = np.ones(B.shape[0], dtype=bool)
        new[1:] = np.any(B[1:] != B[:-1], axis=1)
        group = np.cumsum(new) - 1
        return matern52_cross_minus(A, B[new], group, self._ell[0], self._s[0], P)

    def own_point(self, Xc: FloatArray, levels: IntArray) -> tuple[FloatArray, FloatArray]:
        """Each candidate at its own point: cov_n(theta0(x_c), y_c), the diagonal of
        ``cov_theta0_obs(Xc, Xc, levels)``, and var_n(y_c), ``obs_var(Xc, levels)``, from
        one factor W = L^-1 k_aug(Y_n, c).

        cov = k0(x, x) - k0(x, X_n) K^-1 k_aug(Y_n, (x, l)), with k0(x, x) the level-0 output
        variance (stationary kernel); var as ``obs_var``. In column blocks of ~64 MB of the
        n x m factors.

        Parameters
        ----------
        Xc : ndarray of shape (m, d)
        levels : int ndarray of shape (m,)

        Returns
        -------
        cov, var : ndarrays of shape (m,)
        """
        B = self._centre(Xc, "Xc")
        lc = self._levels(levels, B.shape[0])
        cov, var = np.empty(B.shape[0]), np.empty(B.shape[0])
        blk = max(1, _OWN_BLOCK_ELEMENTS // max(1, self._Xt.shape[0]))
        for i0 in range(0, B.shape[0], blk):
            Bb, lb = B[i0 : i0 + blk], lc[i0 : i0 + blk]
            V = self._theta0_factor(Bb)
            W = self._obs_factor(Bb, lb)
            cov[i0 : i0 + blk] = self._s[0] - np.einsum("ij,ij->j", V, W)
            var[i0 : i0 + blk] = self._obs_var_from(lb, W)
        return cov, var

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
        Wa = self._obs_factor(A, la)
        if A.shape == B.shape and np.array_equal(A, B) and np.array_equal(la, lb):
            # A set against itself (``core.select._Given``: the pending pairs' covariance,
            # once per cluster in J before and after): one factor, not the same one twice.
            G = self._k_aug(A, la, A, la) - Wa.T @ Wa
        else:
            G = self._k_aug(A, la, B, lb) - Wa.T @ self._obs_factor_reused(B, lb)
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
        return self._obs_var_from(lc, self._obs_factor(B, lc))

    def _obs_var_from(self, lc: IntArray, W: FloatArray) -> FloatArray:
        """``obs_var`` given the candidates' levels and their factor W = L^-1 k_aug(Y_n, c)."""
        prior = self._s[0] + np.where(lc >= 1, self._s[lc], 0.0) + self.hyperparameters.noise[lc]
        return np.maximum(prior - np.einsum("ij,ij->j", W, W), 0.0)

    def score(
        self,
        X: FloatArray,
        gammas: Any,
        chunk_size: int = 50_000,
        *,
        max_work: float | None = None,
        progress: Callable[[str, int, int], None] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Posterior mean, sd and failure probability p_n(x) = Phi((gamma - mu) / sd).

        p_n(x) = E_{theta_n}[1{theta_n(x) <= gamma}] (paper eq. (2) and the line after
        it), with theta_n(x) ~ N(mu, sd^2). Computed in chunks of rows so
        the (chunk, n_obs) kernel block stays bounded (at most ``chunk_size`` rows and
        2^24 kernel entries, ~128 MB, per chunk) for pools of millions.

        Each row's sd costs n^2 flops (a triangular solve against the n observations).
        When m n^2 exceeds ``max_work`` the mean stays exact and the sds are bounded
        (``_score_bounded``); ``self.scoring`` says how the last call scored.

        Parameters
        ----------
        X : ndarray of shape (m, d)
        gammas : array-like of shape (g,)
            Failure thresholds.
        chunk_size : int
            Maximum rows per chunk.
        max_work : float, optional
            Flops the sds may take (m n^2 for exact ones); None: exact whatever it costs.
        progress : callable, optional
            ``progress(what, done, total)`` after each chunk.

        Returns
        -------
        mu : ndarray of shape (m,)
        sd : ndarray of shape (m,)
            sqrt of the clipped variance.
        p : ndarray of shape (m, g)
            Where sd is exactly 0 (clipped variance of an observed noise-free point),
            p = 1{mu <= gamma}, the limit of Phi as sd -> 0 (never NaN).
        """
        mu, sigma2, p = self.moments(X, gammas, chunk_size, max_work=max_work, progress=progress)
        return mu, np.sqrt(sigma2), p

    def moments(
        self,
        X: FloatArray,
        gammas: Any,
        chunk_size: int = 50_000,
        *,
        max_work: float | None = None,
        progress: Callable[[str, int, int], None] | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``score`` with the clipped variance sigma2 in place of the sd: what selection
        needs at the pool (``core.select``), bounded as ``score`` is past ``max_work``."""
        g = np.atleast_1d(np.asarray(gammas, dtype=np.float64))
        if g.ndim != 1:
            raise ValueError(f"gammas must be one-dimensional, got shape {g.shape}")
        Xc = self._centre(X)
        n, m = self._Xt.shape[0], Xc.shape[0]
        if self.bounded_scoring(m, max_work) and g.size:
            k = _bound_size(n, m, max_work)  # type: ignore[arg-type]
            return self._score_bounded(Xc, g, chunk_size, max_work, k, progress)  # type: ignore[arg-type]
        self.scoring = {"method": "exact", "rows": int(m)}
        self.sd_exact = None
        return self._score(Xc, g, chunk_size, progress)

    def bounded_scoring(self, m: int, max_work: float | None) -> bool:
        """Whether ``score`` of m rows within ``max_work`` bounds the sds: exact costs
        m n^2, over ``max_work``, and the bound (``_bound_size``) leaves some of it over."""
        if max_work is None or m == 0:
            return False
        n = self._Xt.shape[0]
        k = _bound_size(n, m, max_work)
        return k < n and float(m) * n * n > max_work > float(m) * k * k

    #: How the last ``score`` call scored: method "exact", or "bounded" with its numbers.
    scoring: dict[str, Any] = {"method": "exact"}
    #: Which rows of the last ``score`` call have their exact sd (the rest an upper bound);
    #: None when every row has.
    sd_exact: NDArray[np.bool_] | None = None

    def _score(
        self,
        X: FloatArray,
        gammas: FloatArray,
        chunk_size: int,
        progress: Callable[[str, int, int], None] | None = None,
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
            if progress:
                progress("score pool", sl.stop, m)
        return mu, sigma2, p

    def _score_bounded(
        self,
        X: FloatArray,
        gammas: FloatArray,
        chunk_size: int,
        max_work: float,
        k: int,
        progress: Callable[[str, int, int], None] | None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``_score`` within ``max_work`` flops of sds, for centred X.

        1. The mean, exact: k(x, X_n) alpha costs n flops a row.
        2. An upper bound on every sd: the sd of this GP conditioned on k of its
           observations (``fit.conditioning_subset``, level 0 first; ``_bound_size``:
           k^2 m <= max_work / 8, a loose bound being cheap to tighten where it matters).
           Conditioning on more jointly Gaussian observations never raises a variance, so
           the exact sd is at most this, provided the subset carries the same noise: the
           bound's noise includes the jitter this model's factorisation added to every
           observation (more jitter of its own only raises its variance).
        3. The exact sd where some threshold lies within ``SCORE_DECIDED_Z`` bound-sds of
           the mean, nearest first, as many rows as the rest of the budget buys. Elsewhere
           |gamma - mu| / sd_exact >= |gamma - mu| / sd_bound >= z, so p_n, from either
           sd, is within Phi(-z) < 1e-17 of 0 or 1.
        Rows of step 3 the budget does not reach keep the bound: their p_n leans toward
        1/2 (up for a mean above every threshold, down below one), by at most
        min(p, 1 - p) each, since the exact p_n is on the same side of 1/2 and further
        out; ``self.scoring`` sums that per threshold (``kept_bound_error``).
        """
        from bams_cli.core.gp.fit import conditioning_subset

        n, m = self._Xt.shape[0], X.shape[0]
        rows = conditioning_subset(self.levels_train, self.n_levels, k)
        assert rows is not None  # k < n
        bound = self._on_rows(rows)
        to_bound = self._shift - bound._shift
        mu = np.empty(m)
        sigma2 = np.empty(m)
        step = self._chunk_rows(chunk_size)
        for start in range(0, m, step):
            sl = slice(start, min(start + step, m))
            mu[sl] = self._mean_block(X[sl])[0]
            sigma2[sl] = np.maximum(bound._predict_block(X[sl] + to_bound)[1], 0.0)
            if progress:
                progress("score pool", sl.stop, m)
        gap = np.min(np.abs(gammas[None, :] - mu[:, None]), axis=1)
        sd = np.sqrt(sigma2)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(sd > 0.0, gap / sd, np.where(gap > 0.0, np.inf, 0.0))
        near = np.flatnonzero(z < defaults.SCORE_DECIDED_Z)
        affordable = int(max(0.0, max_work - float(k) * k * m) // (float(n) * n))
        exact = np.sort(near[np.argsort(z[near], kind="stable")[:affordable]])
        for start in range(0, exact.size, step):
            at = exact[start : start + step]
            sigma2[at] = np.maximum(self._predict_block(X[at])[1], 0.0)
            if progress:
                progress("exact sd near the thresholds", start + at.size, exact.size)
        p = np.empty((m, gammas.size))
        for start in range(0, m, step):
            sl = slice(start, min(start + step, m))
            p[sl] = _failure_probability(mu[sl], np.sqrt(sigma2[sl]), gammas)
        kept = np.setdiff1d(near, exact, assume_unique=True)
        self.sd_exact = np.zeros(m, dtype=bool)
        self.sd_exact[exact] = True
        self.scoring = {
            "method": "bounded",
            "rows": int(m),
            "max_work": float(max_work),
            "bound_observations": int(k),
            "near_thresholds": int(near.size),
            "exact_sd_rows": int(exact.size),
            "decided_z": float(defaults.SCORE_DECIDED_Z),
            # per gamma: sum p_n over the pool, and the most the near rows that kept the
            # bound can move it (sum of min(p, 1 - p) over them)
            "p_sum": [float(v) for v in p.sum(axis=0)],
            "kept_bound_error": [float(v) for v in np.minimum(p[kept], 1.0 - p[kept]).sum(axis=0)],
        }
        return mu, sigma2, p


#: ``MFGP.nearest`` measures the distance to a region on at most this many of its points.
_NEAREST_POINTS = 4096


def _bound_size(n: int, m: int, max_work: float) -> int:
    """Observations the sd bound of ``MFGP._score_bounded`` conditions on: k^2 m within
    ``_BOUND_SHARE`` of ``max_work``, at least ``_BOUND_MIN_OBS``, fewer than n."""
    return int(min(n - 1, max(_BOUND_MIN_OBS, math.isqrt(int(max_work * _BOUND_SHARE // m)))))


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
