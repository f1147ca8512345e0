"""The posterior interface that acquisition, selection and estimation code sees.

Selection never touches a concrete GP: it asks a ``Posterior`` for the handful of
covariances the greedy recursion needs (DESIGN.md, "The math, as the code should compute
it"). Tests can hand it a small dense posterior written independently.

One optional fast path sits outside the protocol: ``own_point(Xc, levels)``, each
candidate at its own point: cov_n(theta0(x_c), y_c) (the diagonal of
``cov_theta0_obs(Xc, Xc, levels)``) and ``obs_var(Xc, levels)``, both of shape (m,).
Selection's first screen uses it when a posterior has it (``core.gp.MFGP`` does) and takes
the diagonal of ``cov_theta0_obs`` blocks and ``obs_var`` otherwise. ``MFGP`` has three
more that selection uses when present: ``localised`` (a cluster's factors remembered),
``bounded_scoring`` and ``moments`` (the pool's sds within a flop budget, with
``scoring`` saying how).

Notation: a pool point ``x`` (row of ``X``) and a candidate observation ``c = (x_c, l)``:
segment coordinates ``x_c`` simulated at fidelity level ``l`` (0 = high fidelity), whose
outcome is ``y_c = theta0(x_c) + alpha_l(x_c) + eps_l``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class Posterior(Protocol):
    """Posterior of theta0 and of future observations, given the observations so far."""

    @property
    def n_levels(self) -> int:
        """Number of fidelity levels L + 1 (level 0 is the high-fidelity simulator)."""
        ...

    @property
    def lengthscales0(self) -> FloatArray:
        """Level-0 (theta0) Matern lengthscales, shape (d,); used to scale the pool for K-means."""
        ...

    def predict_theta0(self, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Posterior mean and variance of theta0 at X.

        Parameters
        ----------
        X : ndarray of shape (n, d)

        Returns
        -------
        mu : ndarray of shape (n,)
        sigma2 : ndarray of shape (n,)   (clipped at 0)
        """
        ...

    def cov_theta0_obs(self, X: FloatArray, Xc: FloatArray, levels: IntArray) -> FloatArray:
        """cov_n(theta0(x), y_c) for pool points x and candidate observations c.

        cov_n(theta0(x), y_c) = k0(x, x_c) - k0(x, X_n) K^-1 k_aug(Y_n, (x_c, l_c)).
        Observation noise does not enter: theta0(x) is noise-free.

        Parameters
        ----------
        X : ndarray of shape (n, d)
        Xc : ndarray of shape (m, d)
        levels : int ndarray of shape (m,)

        Returns
        -------
        C : ndarray of shape (n, m)
        """
        ...

    def cov_obs_obs(
        self,
        Xa: FloatArray,
        levels_a: IntArray,
        Xb: FloatArray,
        levels_b: IntArray,
        same: NDArray[np.bool_] | None = None,
    ) -> FloatArray:
        """cov_n(y_a, y_b) between two sets of candidate observations.

        Prior part k_aug((x_a, a), (x_b, b)) = k0 + [a == b >= 1] k_a, minus the data term.
        The noise tau_l^2 is added where ``same[i, j]`` is True (the two are the same
        future observation). When ``same`` is None it is taken as "identical coordinates
        and identical level".

        Returns
        -------
        G : ndarray of shape (len(Xa), len(Xb))
        """
        ...

    def obs_var(self, Xc: FloatArray, levels: IntArray) -> FloatArray:
        """var_n(y_c) = diag of cov_obs_obs(c, c) including the noise tau_l^2; shape (m,)."""
        ...
