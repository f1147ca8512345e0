"""The screened design's variance with phase 2 conditioned on each failure, by screen share.

    .venv/bin/python docs/suite/screen_exact.py run PROBLEM [--data-seed N] [--seeds 0-4] [--trials 2]
    .venv/bin/python docs/suite/screen_exact.py table

``benchmark.screen_default`` and ``screen_design.py run`` average phase 2's variance
sum_{S1} y (1 - pi2)/(pi1^2 pi2) over 4 screens. That term is heavy-tailed: a failure the
screen takes at small pi1 lands in S1 in few screens, and when it does with pi2 < 1 it adds
(1 - pi2)/(pi1^2 pi2), hundreds of times its share of the mean. Four screens either miss it
(too low) or catch it (too high). Here each failure i's expected term is measured on its own:

    E[phase 2] = sum_i pi1_i E[(1 - pi2_i)/(pi1_i^2 pi2_i) | i in S1]
               = sum_i E[(1 - pi2_i)/(pi1_i pi2_i) | i in S1],

and recall's phase 2 share sum_i pi1_i E[pi2_i | i in S1], where for each of ``--trials``
draws of S1 (Poisson at pi1, as ``core.screen.screen_design`` gives it) every unknown failure
i is put into S1, the model is refitted on S1's true cheap values at the discovery model's
hyperparameters (as the benchmark refits), and pi2 is ``core.screen.confirm_design``'s over
S1 with K2 = K - c |S1|. Phase 1's term sum_U y (1 - pi1)/pi1 is exact. One refit per
failure per trial: for problems with few failures in U (av_like: 7 to 13). As in
``screen_design.py run``, every segment of S1 is paid for and appended at the cheap level,
also the few whose cheap result the log already holds (the discovery pairs), which the tool
and ``benchmark.screen_default`` skip.

``run`` appends one JSON line per seed to docs/suite/screen_exact/[dataN-]PROBLEM.jsonl;
``table`` writes docs/suite/screen_exact.md.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "screen_exact"
sys.path.insert(0, str(HERE))
import estimate_refit as er  # noqa: E402
import screen_design as sd  # noqa: E402

SHARES = (0.3, 0.4, 0.5)


def run(problem: str, seeds: list[int], trials: int) -> None:
    from bams_cli.core import screen as sc

    su = sd._setup(problem, "exact")
    K, c, prior = su.prob.K, su.cost, su.prior
    OUT.mkdir(exist_ok=True)
    for seed, base, st in sd._seed_states(su, seeds):
        U, fU, F, Fk = st.U, st.fU, st.F, st.Fk
        k = min(K, U.size)
        var_u = int(fU.sum()) * (U.size - k) / k
        fail_pos = np.flatnonzero(fU)
        if var_u <= 0:  # no failure left unknown, or K covers U: nothing to compare
            print(f"seed {seed}: uniform's variance is 0 (no unknown failure?); skipped")
            continue
        row: dict = {
            "problem": problem, "data_seed": sd.DATA_SEED, "seed": seed, "trials": trials,
            "F": F, "F_unknown": int(fail_pos.size), "K": K, "cost": c,
        }  # fmt: skip
        for share in SHARES:
            pi1 = sc.screen_design(st.p[U], K=K, cost=c, share=share, posterior=prior).pi
            rng = np.random.default_rng(seed * 100 + 13)
            v2 = np.zeros((trials, fail_pos.size))
            found = np.zeros((trials, fail_pos.size))
            for t in range(trials):
                drawn = rng.random(U.size) < pi1
                for j, i in enumerate(fail_pos):
                    s1 = drawn.copy()
                    s1[i] = True
                    sel = np.flatnonzero(s1)
                    p2 = sd._refit_on_screen(base, su.scratch / f"x-{seed}-{t}-{j}", st, sel)
                    K2 = min(sc.confirm_budget(K, c, sel.size), float(sel.size))
                    pi2 = sc.confirm_design(p2[sel], K2=K2, posterior=prior).pi
                    q = float(pi2[np.searchsorted(sel, i)])
                    v2[t, j] = (1.0 - q) / (pi1[i] * q)
                    found[t, j] = pi1[i] * q
            V1 = sc.phase1_variance(fU, pi1)
            row[str(share)] = {
                "phase1": V1 / var_u,
                "var": (V1 + float(v2.mean(axis=0).sum())) / var_u,
                "recall": (Fk + float(found.mean(axis=0).sum())) / F,
                "pi1_failures": np.round(pi1[fail_pos], 4).tolist(),
            }
        path = OUT / f"{f'data{sd.DATA_SEED}-' if sd.DATA_SEED else ''}{problem}.jsonl"
        with open(path, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


def table() -> None:
    lines = [
        "# The screened design's variance, phase 2 conditioned on each failure",
        "",
        "`docs/suite/screen_exact.py` (its docstring says how). var: the design's variance "
        "over a uniform Poisson design's of K level-0 runs, phase 1 exact and phase 2 "
        "conditioned on each unknown failure being screened (so its heavy tail is measured, "
        "not sampled by 4 screens); phase 1: its share of that ratio; recall: failures in "
        "hand after the estimate over all failures. Mean [max] over seeds.",
        "",
        "| problem | data seed | seeds | share | phase 1 | var / uniform | recall |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for path in sorted(OUT.glob("*.jsonl")):
        rows = [json.loads(x) for x in path.read_text().splitlines() if x]
        for share in SHARES:
            got = [r[str(share)] for r in rows if str(share) in r]
            if not got:
                continue
            v = [g["var"] for g in got]
            lines.append(
                f"| {rows[0]['problem']} | {rows[0]['data_seed']} | {len(got)} | {share} | "
                f"{statistics.mean(g['phase1'] for g in got):.3f} | "
                f"{statistics.mean(v):.3f} [{max(v):.3f}] | "
                f"{statistics.mean(g['recall'] for g in got):.3f} |"
            )
    lines += ["", NOTES.replace("\n", " ")]
    (HERE / "screen_exact.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


#: What the table shows, as measured when it was made.
NOTES = """Measured 2026-11-27 (20:00-20:30, 2 trials per seed, 5 seeds each). On the suite's
av_like (data seed 0) the screen at the shipped share 0.3 has 0.04-0.07 of uniform's
variance, almost all of it phase 1's, and 0.4 would be a little better (0.05 against 0.06
on average); on the held-out instance of data seed 2 it has 0.31 [0.41], against the
benchmark's 0.49 [1.12] from 4 screens per run (docs/suite/heldout_default.md): that
instance's failures sit where the discovery model puts little risk (pi1 0.05-0.2 for most),
so phase 1 alone is 0.13-0.20 and the refit leaves some screened failures at pi2 near 0.4.
A larger screen lowers phase 1 and raises phase 2 about as much (share 0.4: 0.33, 0.5:
0.39), so issue 12's 1/5 is out of reach there for this design at any share measured. Data
seed 1 lies between: 0.13 [0.19] at 0.3 (the benchmark's 4 screens: 0.13 [0.19]), 0.10 at
0.4. A share of 0.4 would lower the variance on data seeds 0 and 1 by a quarter and raise it
on data seed 2 by a fifteenth; the suite's toy2d and gap_sim did not gain from it
(docs/suite/screen_design.md: 0.03 [0.10] against 0.02 [0.04], 0.39 both), so 0.3 stays."""


def main(argv: list[str]) -> None:
    if "--data-seed" in argv:
        i = argv.index("--data-seed")
        sd.DATA_SEED = int(argv[i + 1])
        argv = argv[:i] + argv[i + 2 :]
    if argv[:1] == ["table"]:
        table()
    elif argv[:1] == ["run"] and len(argv) > 1:
        run(argv[1], *er.seeds_and_trials(argv, "0-4", 2))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
