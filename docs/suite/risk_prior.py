"""The Beta prior on lam (``defaults.RISK_MIX_PRIOR``) on the suite: variance against
uniform and coverage of the default two-stage estimate design under other priors.

    .venv/bin/python docs/suite/risk_prior.py "1,1;1,3;0.5,3" 0.5 30 [workers]

Arguments: priors (a,b pairs separated by ';'), stage-1 shares, draws per run, workers.
Reads the suite's saved runs (``bams-cli benchmark --protocol suite --save-arrays --out
/tmp/suite-arrays``, as docs/suite/estimate_design.py) and draws the design for the BAMS
runs of every problem, seeds 0-9, with ``core.evaluate.staged_trials``. Prints a table per
prior; docs/suite/risk_prior.md holds the run that chose the default.
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


def one(args):
    problem, seed, prior, share, trials = args
    warnings.simplefilter("ignore")
    from bams_cli.core.evaluate import staged_trials

    z = np.load(F / problem / "runs.npz")
    fail = z["f0"] <= float(z["gamma"])
    known, p = z[f"bams-{seed}-known"], z[f"bams-{seed}-p"]
    r = staged_trials(
        p, fail, K=float(z["K"]), known=known, n_trials=trials, share=share, prior=prior,
        rng=np.random.default_rng(seed),
    )  # fmt: skip
    inside = (r.ci_low <= r.rate) & (r.rate <= r.ci_high)
    return {
        "problem": problem, "seed": seed, "prior": prior, "share": share,
        "ratio": r.var / r.var_uniform, "cov": float(inside.mean()),
        "below": float((r.ci_high < r.rate).mean()), "lam": float(r.lam.mean()),
    }  # fmt: skip


def main(argv):
    priors = [tuple(map(float, s.split(","))) for s in argv[0].split(";")]
    shares = [float(s) for s in argv[1].split(",")]
    trials = int(argv[2])
    workers = int(argv[3]) if len(argv) > 3 else 1
    jobs = [
        (pb, s, pr, sh, trials)
        for pr in priors
        for sh in shares
        for pb in PROBLEMS
        for s in range(10)
    ]
    t0 = time.time()
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
        rows = list(ex.map(one, jobs))
    for pr in priors:
        for sh in shares:
            print(f"prior {pr} share {sh}")
            for pb in PROBLEMS:
                rs = [r for r in rows if (r["problem"], r["prior"], r["share"]) == (pb, pr, sh)]
                rat = [r["ratio"] for r in rs]
                print(
                    f"  {pb:13s} ratio {np.mean(rat):.3f} [max {np.max(rat):.3f}] "
                    f"cov {np.mean([r['cov'] for r in rs]):.3f} "
                    f"below {np.mean([r['below'] for r in rs]):.3f} "
                    f"lam {np.mean([r['lam'] for r in rs]):.2f}"
                )
    print("wall", time.time() - t0)


if __name__ == "__main__":
    main(sys.argv[1:])
