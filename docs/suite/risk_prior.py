"""The Beta prior on lam (``defaults.RISK_MIX_PRIOR``) on the suite: variance against
uniform and coverage of the default staged estimate design under other priors.

    .venv/bin/python docs/suite/risk_prior.py "1,1;1,3;0.5,3" 0.5 30 [workers] \
        [--strategies bams,mcm-gp] [--anchor-sd 1.0] [--taus 0.5,1] [--arrays FOLDER]
    .venv/bin/python docs/suite/risk_prior.py --fixed-lam 0,0.1,0.25,0.5 [--strategies ...]

Arguments: priors (a,b pairs separated by ';'), stage-1 shares, draws per run, workers;
the strategies whose runs to draw on (default bams), the posterior's anchor sd (default
``defaults.RISK_ANCHOR_SD``), the calibration shapes tau it weighs (default
``core.design.TAUS``) and the folder of saved runs (default /tmp/suite-arrays). Reads the suite's saved runs (``bams-cli benchmark --protocol
suite --save-arrays --out /tmp/suite-arrays``, as docs/suite/estimate_design.py) and draws
the design for the runs of every problem, seeds 0-9, with ``core.evaluate.staged_trials``.
Prints a table per prior and share; docs/suite/risk_prior.md holds the runs that chose the
defaults.
"""

import multiprocessing as mp
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

F = Path("/tmp/suite-arrays")
PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")


def _use_taus(taus):
    """Make ``taus`` the calibration shapes every design function weighs (this process)."""
    from bams_cli.core import design as dz

    if taus is None:
        return
    dz.TAUS = tuple(taus)
    dz.risk_posterior.__kwdefaults__["taus"] = dz.TAUS
    dz.risk_norms.__defaults__ = (dz.TAUS,)


def one(args):
    problem, strategy, seed, prior, share, anchor_sd, trials, taus, folder = args
    warnings.simplefilter("ignore")
    from bams_cli.core.evaluate import staged_trials

    _use_taus(taus)
    F = Path(folder)

    z = np.load(F / problem / "runs.npz")
    fail = z["f0"] <= float(z["gamma"])
    known, p = z[f"{strategy}-{seed}-known"], z[f"{strategy}-{seed}-p"]
    r = staged_trials(
        p, fail, K=float(z["K"]), known=known, n_trials=trials, share=share, prior=prior,
        anchor_sd=anchor_sd, rng=np.random.default_rng(seed),
    )  # fmt: skip
    from bams_cli.core import design as dz

    U = np.flatnonzero(~known)
    K1 = share * min(float(z["K"]), U.size)
    pi1 = dz.choose_design(p[U], K=K1, posterior=dz.risk_posterior([], prior=prior)).pi
    inside = (r.ci_low <= r.rate) & (r.rate <= r.ci_high)
    return {
        "problem": problem, "strategy": strategy, "seed": seed, "prior": prior, "share": share,
        "ratio": r.var / r.var_uniform, "cov": float(inside.mean()),
        "f_u": int(fail[U].sum()), "f_stage1": float(pi1[fail[U]].sum()),
        "below": float((r.ci_high < r.rate).mean()), "lam": float(r.lam.mean()),
    }  # fmt: skip


def fixed_lam(lams: list[float], strategies: list[str]) -> None:
    """The exact variance over uniform's of a single-stage calibrated design at fixed lam
    (tau 1), mean [max] over seeds 0-9: what a design that knew how far to trust p_n would
    get; and its recall (known failures plus sum pi over U's, over all failures) over
    uniform level-0 sampling's expectation (B + K) / N at the same cost."""
    from bams_cli import benchmark as B
    from bams_cli.core import design as dz

    for pb in PROBLEMS:
        z = np.load(F / pb / "runs.npz")
        fail = z["f0"] <= float(z["gamma"])
        proto = B.PROTOCOLS[pb]
        uniform = (proto.m1 + proto.mb * (proto.n_batches - 1) + float(z["K"])) / fail.size
        for st in strategies:
            ratios, recalls = [], []
            for seed in range(10):
                known, p = z[f"{st}-{seed}-known"], z[f"{st}-{seed}-p"]
                U = np.flatnonzero(~known)
                K = min(float(z["K"]), U.size)
                fu, u = fail[U], dz.relative_risk(p[U])
                v_u = fu.sum() * (U.size - K) / K
                row, rec = [], []
                for lam in lams:
                    pi = dz.calibrated_design(lam + (1.0 - lam) * u, K=K)
                    row.append(float(((1.0 - pi[fu]) / pi[fu]).sum()) / v_u)
                    rec.append((fail[known].sum() + pi[fu].sum()) / fail.sum() / uniform)
                ratios.append(row)
                recalls.append(rec)
            print(
                f"  {pb:13s} {st:7s} fixed lam "
                + " / ".join(
                    f"{lam:g}: {r:.3f} [{m:.3f}] recall {c:.2f}x"
                    for lam, r, m, c in zip(
                        lams,
                        np.mean(ratios, axis=0),
                        np.max(ratios, axis=0),
                        np.mean(recalls, axis=0),
                        strict=True,
                    )
                )
            )


def main(argv):
    global F
    from bams_cli import defaults

    strategies, anchor_sd = ["bams"], defaults.RISK_ANCHOR_SD
    if "--arrays" in argv:
        i = argv.index("--arrays")
        F = Path(argv[i + 1])
        del argv[i : i + 2]
    if "--fixed-lam" in argv:
        i = argv.index("--fixed-lam")
        lams = [float(x) for x in argv[i + 1].split(",")]
        if "--strategies" in argv:
            strategies = argv[argv.index("--strategies") + 1].split(",")
        fixed_lam(lams, strategies)
        return
    taus, folder = None, str(F)
    for flag in ("--strategies", "--anchor-sd", "--taus"):
        if flag in argv:
            i = argv.index(flag)
            value = argv[i + 1]
            del argv[i : i + 2]
            if flag == "--strategies":
                strategies = value.split(",")
            elif flag == "--taus":
                taus = tuple(float(t) for t in value.split(","))
            else:
                anchor_sd = None if value == "none" else float(value)
    priors = [tuple(map(float, s.split(","))) for s in argv[0].split(";")]
    shares = [float(s) for s in argv[1].split(",")]
    trials = int(argv[2])
    workers = int(argv[3]) if len(argv) > 3 else 1
    jobs = [
        (pb, st, s, pr, sh, anchor_sd, trials, taus, folder)
        for pr in priors
        for sh in shares
        for pb in PROBLEMS
        for st in strategies
        for s in range(10)
    ]
    t0 = time.time()
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
        rows = list(ex.map(one, jobs))
    for pr in priors:
        for sh in shares:
            print(f"prior {pr} share {sh} anchor sd {anchor_sd} taus {taus or 'default'}")
            for pb in PROBLEMS:
                for st in strategies:
                    rs = [
                        r
                        for r in rows
                        if (r["problem"], r["strategy"], r["prior"], r["share"]) == (pb, st, pr, sh)
                    ]
                    rat = [r["ratio"] for r in rs]
                    print(
                        f"  {pb:13s} {st:7s} ratio {np.mean(rat):.3f} [max {np.max(rat):.3f}] "
                        f"cov {np.mean([r['cov'] for r in rs]):.3f} "
                        f"below {np.mean([r['below'] for r in rs]):.3f} "
                        f"lam {np.mean([r['lam'] for r in rs]):.2f} "
                        f"failures in U {np.mean([r['f_u'] for r in rs]):.0f}, "
                        f"expected in stage 1 {np.mean([r['f_stage1'] for r in rs]):.1f}"
                    )
    print("wall", time.time() - t0)


if __name__ == "__main__":
    main(sys.argv[1:])
