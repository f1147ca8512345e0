"""Does the level-1 discrepancy absorb theta0's misfit? One theta0 kernel against two.

    .venv/bin/python docs/suite/theta0_capacity.py /tmp/fresh braking 0 1 2 3 4 5 6 7

Reads the workspaces ``fresh_problems.py run`` keeps after batch 3
(``runs/PROBLEM-sN.after-batch-3``) and the problem's truth, and fits, with the tool's
priors re-implemented here (LogNormal on every variance and lengthscale in standardised
units, the lengthscales' BoTorch dimension-scaled prior, the discrepancy's mode at the
pairs' variance with its floor of 0.01, the GLS constant mean and level-1 offset; Matern
5/2 ARD kernels; L-BFGS-B with numerical gradients, 4 starts), the two-level model twice:

* ``1 comp``: theta0 with one kernel, as the tool fits it (``core/gp``);
* ``2 comp``: theta0 as the sum of two kernels (the second's variance prior mode 0.1 of
  the first's), the discrepancy and noises as before.

Each line prints the fitted level-1 discrepancy sd (sqrt of discrepancy + both noises,
``checks.fitted_discrepancy_sd``) over the pool's sd(f1 - f0), issue 11's factor-2 check.
Where the tool frees a level's scale (``priors.shows_scale``) this sketch does not, so
such a run (braking seed 1) is compared at rho 1. It is an experiment, not the tool.

``--level1-only`` instead fits scikit-learn's GP to the level-1 runs alone with one Matern
kernel and with two, and prints their log marginal likelihoods and the white noise each
leaves: how much of the cheap level one stationary kernel cannot hold.
"""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import polars as pl
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize

from bams_cli.core.gp.priors import paired_values
from bams_cli.pipeline.fitting import _training_data
from bams_cli.settings import load_settings
from bams_cli.state.workspace import Workspace

warnings.filterwarnings("ignore")


def _matern(A: np.ndarray, B: np.ndarray, ls: np.ndarray) -> np.ndarray:
    a, b = A / ls, B / ls
    d2 = np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T, 0)
    r = np.sqrt(5 * d2)
    return (1 + r + r * r / 3) * np.exp(-r)


def fit(X: np.ndarray, lv: np.ndarray, y: np.ndarray, ncomp: int, seed: int, pairs_var: float):
    """MAP of the two-level model with ``ncomp`` theta0 kernels; y standardised."""
    n, d = X.shape
    ell_loc = math.sqrt(2) + 0.5 * math.log(d) + np.log(np.ptp(X, 0) + 1e-12)

    def mode_loc(mode: float, s: float) -> float:
        return math.log(mode) + s * s

    locs: list[float] = []
    scs: list[float] = []
    for c in range(ncomp):
        locs += [mode_loc(1.0 if c == 0 else 0.1, 1.5), *ell_loc]
        scs += [1.5] + [math.sqrt(3)] * d
    locs += [mode_loc(max(pairs_var, 0.01), 1.0), *ell_loc]
    scs += [1.0] + [math.sqrt(3)] * d
    locs += [mode_loc(3e-4, 1.0), mode_loc(3e-3, 2.0)]
    scs += [1.0, 2.0]
    loc, sc = np.array(locs), np.array(scs)
    H = np.c_[np.ones(n), (lv == 1).astype(float)]
    m1 = lv == 1

    def unpack(t: np.ndarray):
        i, comps = 0, []
        for _ in range(ncomp):
            comps.append((np.exp(t[i]), np.exp(t[i + 1 : i + 1 + d])))
            i += 1 + d
        disc = (np.exp(t[i]), np.exp(t[i + 1 : i + 1 + d]))
        i += 1 + d
        return comps, disc, np.exp(t[i]), np.exp(t[i + 1])

    def neg_log_post(t: np.ndarray) -> float:
        comps, disc, n0, n1 = unpack(t)
        K = sum(s * _matern(X, X, ls) for s, ls in comps)
        K = K + np.outer(m1, m1) * disc[0] * _matern(X, X, disc[1])
        K[np.diag_indices(n)] += np.where(m1, n1, n0) + 1e-8
        try:
            cf = cho_factor(K, lower=True)
        except np.linalg.LinAlgError:
            return 1e10
        KiH = cho_solve(cf, H)
        beta = np.linalg.solve(H.T @ KiH, KiH.T @ y)
        r = y - H @ beta
        ll = -0.5 * r @ cho_solve(cf, r) - np.log(np.diag(cf[0])).sum()
        u = (t - loc) / sc
        return -(ll + np.sum(-t - 0.5 * u * u))

    rng = np.random.default_rng(seed)
    mode = loc - sc**2
    best = None
    for k in range(4):
        start = mode if k == 0 else rng.normal(mode, sc)
        res = minimize(neg_log_post, start, method="L-BFGS-B", options={"maxiter": 300})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    return unpack(best.x)


def _study(folder: Path, problem: str, seed: int):
    ws = Workspace(folder / "runs" / f"{problem}-s{seed}.after-batch-3")
    st = load_settings(ws.root)
    ids, X = ws.read_pool()
    idx, lv, y = _training_data(ws, ids, X, st.n_levels)
    truth = pl.DataFrame({"segment_id": ids}).join(
        pl.read_parquet(folder / problem / "truth.parquet"), on="segment_id", how="left"
    )
    true_sd = float(np.std(truth["value_1"].to_numpy() - truth["value_0"].to_numpy()))
    return X[idx], lv, y, idx, true_sd


def main(argv: list[str]) -> None:
    level1_only = "--level1-only" in argv
    argv = [a for a in argv if a != "--level1-only"]
    folder, problem, seeds = Path(argv[0]), argv[1], [int(s) for s in argv[2:]]
    for s in seeds:
        X, lv, y, idx, true_sd = _study(folder, problem, s)
        if level1_only:
            from sklearn.gaussian_process import GaussianProcessRegressor
            from sklearn.gaussian_process.kernels import ConstantKernel as C
            from sklearn.gaussian_process.kernels import Matern
            from sklearn.gaussian_process.kernels import WhiteKernel as W

            A, b = X[lv == 1], y[lv == 1]
            r = np.ptp(A, 0)

            def m(scale: float, r: np.ndarray = r) -> Matern:
                return Matern(r * scale, nu=2.5, length_scale_bounds=(1e-3, 1e4))

            one = C(1.0) * m(1) + W(1e-2, (1e-8, 1e2))
            two = C(1.0) * m(1) + C(0.05) * m(1 / 3) + W(1e-2, (1e-8, 1e2))
            out = []
            for name, k in (("one", one), ("two", two)):
                g = GaussianProcessRegressor(k, normalize_y=True, n_restarts_optimizer=3,
                                             random_state=0).fit(A, b)  # fmt: skip
                white = math.sqrt(g.kernel_.k2.noise_level) * float(np.std(b))
                out.append(
                    f"{name} kernel: log ML {g.log_marginal_likelihood_value_:.1f}, "
                    f"white noise sd {white:.2f}"
                )
            print(problem, s, " | ".join(out), flush=True)
            continue
        ybar, ystd = y.mean(), y.std()
        ys = (y - ybar) / ystd
        y0, y1 = paired_values(idx, lv, ys, 1)
        pv = float(np.var(y1 - y0, ddof=1)) if y0.size >= 3 else 0.01
        out = []
        for nc in (1, 2):
            comps, disc, n0, n1 = fit(X, lv, ys, nc, s, pv)
            ratio = math.sqrt(disc[0] + n0 + n1) * ystd / true_sd
            sds = ", ".join(f"{math.sqrt(c[0]) * ystd:.3g}" for c in comps)
            out.append(
                f"{nc} comp: fitted / true {ratio:.2f} (discrepancy sd "
                f"{math.sqrt(disc[0]) * ystd:.3g}, theta0 sd {sds})"
            )
        print(problem, s, " | ".join(out), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
