"""Multifidelity Gaussian process: MAP training and the posterior BAMS needs.

Model (paper section 3, "Multifidelity sampling"; DESIGN.md "The math"). Levels
l = 0..L, level 0 the high-fidelity simulator. An observation of segment x at level l is

    y = m + b_l + theta0(x) + alpha_l(x) + eps_l,   alpha_0 = 0,  b_0 = 0,  eps_l ~ N(0, tau_l^2),

with a constant mean m, a constant offset b_l per cheap level, theta0 ~ GP(0, k0) and independent alpha_l ~ GP(0, k_l), each a
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
are run to convergence, BLAS pinned to one thread. The constant mean
and the level offsets are profiled out in closed form (generalised least squares,
beta_hat = (H'K^-1 H)^-1 H'K^-1 y, ``objective.mean_basis``) at every evaluation rather
than optimised: by the envelope theorem the gradient of the profiled objective is the usual
one evaluated at beta_hat. They are then plug-in estimates (their own uncertainty is not
propagated into predictions, as for every other hyperparameter).

The package keeps the pieces apart the way scikit-learn keeps kernels apart from its
regressor: ``hyperparameters`` (the parameters and their log packing), ``priors`` (every
prior default, defined once), ``objective`` (negative log posterior and gradient), ``fit``
(the optimiser), ``model`` (the conditioned posterior), ``checks`` (self-checks of a fitted
model against its own data) and ``transform`` (the monotone output transform).

Numerics: Cholesky with escalating relative jitter (``cholesky``, the jitter recorded on the
model); predictions reuse the factor L and alpha = K^-1 (y - H beta) computed once at
construction (GPML Alg. 2.1).
"""

from bams_cli.core.gp._numerics import GPFitError, check_data, cholesky, standardise
from bams_cli.core.gp.fit import fit_mfgp, fit_transformed
from bams_cli.core.gp.hyperparameters import Hyperparameters, _pack
from bams_cli.core.gp.model import MFGP, _failure_probability
from bams_cli.core.gp.objective import _MAPObjective, mean_basis
from bams_cli.core.gp.priors import DEFAULT_PRIORS, PriorSpec, _Priors
from bams_cli.core.gp.transform import OutputTransform

__all__ = [
    "DEFAULT_PRIORS",
    "GPFitError",
    "Hyperparameters",
    "MFGP",
    "PriorSpec",
    "check_data",
    "cholesky",
    "fit_mfgp",
    "fit_transformed",
    "OutputTransform",
    "mean_basis",
    "standardise",
    "_MAPObjective",
    "_Priors",
    "_failure_probability",
    "_pack",
]
