"""The shipped default estimate (``--screen auto``) on fresh realisations of the suite.

    .venv/bin/python docs/suite/heldout_default.py run DATA_SEED [PROBLEM ...] [--seeds N]
    .venv/bin/python docs/suite/heldout_default.py table

Each problem is generated again with another data seed (as docs/suite/heldout_estimate.py
makes them: another latent map, failure regions, bias; digits another split) and
``bams-cli benchmark`` runs BAMS on it with the defaults as shipped, seeds 0..N-1. The
benchmark measures the default estimate as the suite table does: where ``--screen auto``
screens, the screened design drawn ``benchmark.SCREEN_TRIALS`` times per run, each screen
refitted on its true cheap values (``benchmark.screen_default``); elsewhere the staged
design drawn ``benchmark.STAGED_TRIALS`` times. Nothing here was used to choose the
threshold or the share.

Results accumulate in docs/suite/heldout_default.json (one entry per data seed and
problem); ``table`` writes docs/suite/heldout_default.md from it.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bams_cli import benchmark as B
from bams_cli import defaults

HERE = Path(__file__).resolve().parent
OUT = HERE / "heldout_default.json"
PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")


#: What the table says, as measured when it was made.
NOTES = """Measured 2026-11-27 at ae071a9 (data seeds 1 and 2, 5 seeds each; the refit-size
condition of --screen auto added after it never applies at these pool sizes). --screen auto
screened every seed of toy2d, av_like and gap_sim and no seed of weak_cheap, digits and
rare_regions, as on the suite. Where it screened, the default had 0.02-0.39 of uniform's
variance on average, except av_like on data seed 2: 0.49, with one seed at 1.12 (the staged
design had 0.37 there, docs/suite/heldout_estimate.md): that instance's discovery model
leaves failures at a relative risk of 0.01, and the screen's pi1, drawn from it, takes them
rarely. Issue 12's 1/5 on av_like held on data seed 1 (0.13, every seed under 0.2) and not
on data seed 2. Where it did not screen, the staged design (since the rerun below, under
the prior for a cheap level that does not track level 0) has at most 1.08 of uniform's
variance on any seed. 59 of 60 realised estimates' 90% intervals held the true rate, the
other above it. Recall over plain MC: 32-40x (toy2d), 10-12x (av_like), 7-8x (gap_sim);
1.3-1.6x on weak_cheap and digits and 0.8x and 2.2x on rare_regions, short of issue 11's
asks. Rerun
for toy2d, av_like and gap_sim on 2026-11-27 (20:10) with the screened interval's "mean"
allowance: the designs' numbers are the same to the digit and all 30 screened realised
intervals still hold the rate, at 1.5-2.1 times the rate on toy2d (5.1-7.4 before),
3.7-4.5 on av_like (7.3-9.3) and 1.5-1.6 on gap_sim (2.1). av_like's 0.49 [1.12] on data
seed 2 is 4 screens' average of a heavy-tailed phase 2; measured with phase 2 conditioned on
each failure (docs/suite/screen_exact.md) the same runs' screened variance is 0.31 [0.41] of
uniform's, still above issue 12's 1/5, and a larger screen does not bring it under (share
0.4: 0.33, 0.5: 0.39). Rerun for weak_cheap, digits and rare_regions on 2026-11-27 (23:15)
once the prior on lam followed the fitted cheap level (Beta(1, 0.5) where it does not track
level 0, docs/suite/weak_cheap_prior.md): their worst seeds 0.96-1.21 -> 0.94-1.08 of
uniform's variance (rare_regions' data seed 2: 1.21 -> 1.08), recall 1.3-1.6x plain MC on
weak_cheap and digits (1.3-1.8x before) and 0.8x and 2.2x on rare_regions (0.9x, 2.3x); 29
of 30 realised intervals held the rate, the miss (digits, data seed 1) above it. Rerun for
av_like on data seed 2 on 2026-11-29 (06:52-06:54, 5 seeds) once the screen's confirmation
planned pi2 under Beta(0.1, 10) where the cheap level tracks level 0
(docs/suite/screen_confirm_prior.md): 0.49 [1.12] -> 0.21 [0.38] of uniform's variance (4
screens per run; conditioned on each failure the same change is 0.31 [0.41] -> 0.19 [0.25]),
recall 12.2x -> 12.3x plain MC, all 5 realised intervals holding the rate; the other
screened rows were measured before it. Rerun for toy2d and av_like on both data seeds on
2026-11-29 (17:38-17:50 at 09de138) once the screen took the open cheap-level leads with
certainty in both phases (core.screen): av_like's variance over uniform's 0.13 [0.19] ->
0.12 [0.18] on data seed 1 and 0.21 [0.38] -> 0.15 [0.19] on data seed 2, so every seed of
both instances is now under issue 12's 1/5; recall over plain MC 9.7x -> 9.4x and 12.3x
-> 13.7x; toy2d 0.03 [0.07] -> 0.02 [0.04] and 0.02 [0.04] -> 0.01 [0.02], recall 39.8x
-> 52.9x and 32.4x -> 40.8x; all 20 realised intervals held the rate. av_like's data
seeds 3 and 4 the same day (17:52-17:57 at 09de138; 0.25 [0.38] and 0.20 [0.25] before,
README's estimate section): 0.17 [0.20] and 0.17 [0.23], recall 11.1x and 8.2x plain MC,
9 of 10 realised intervals holding the rate, the other above it. On the four held-out
instances av_like's mean is under 1/5 on each; two single seeds reach 0.20 and 0.23."""


def run(data_seed: int, problems: tuple[str, ...], seeds: int) -> None:
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    for problem in problems:
        original, sample = B.GENERATORS[problem], B.SAMPLE_DATA
        B.GENERATORS[problem] = lambda n, _seed, _g=original: _g(n, data_seed)
        t0 = time.perf_counter()
        try:
            with tempfile.TemporaryDirectory(prefix="bams-heldout-default-") as tmp:
                # Not the committed sample data (data seed 0): a pool generated afresh.
                B.SAMPLE_DATA = Path(tmp) / "no-sample-data"
                res = B.run_benchmark(
                    problem, seeds=seeds, quick=False, out_dir=Path(tmp) / "out",
                    strategies=["bams", "mc"], level0_share=defaults.LEVEL0_SHARE, workers=2,
                    progress=None,
                )  # fmt: skip
        finally:
            B.GENERATORS[problem], B.SAMPLE_DATA = original, sample
        b, m = res["bams"], res["mc"]
        rate = res["setup"]["rate"]
        real = [e for e in b["realised_estimates"] if e]
        results[f"{data_seed}/{problem}"] = {
            "data_seed": data_seed,
            "problem": problem,
            "rate": rate,
            "seconds": time.perf_counter() - t0,
            "screened": b["screened_seeds"],
            "var": b["per_seed_var_default"],
            "recall": b["per_seed_recall_default"],
            "mc_recall": m["per_seed_recall"],
            "realised": [[e["p_hat"], e["ci_low"], e["ci_high"]] for e in real],
        }
        OUT.write_text(json.dumps(results, indent=1) + "\n")
        print(problem, data_seed, _line(results[f"{data_seed}/{problem}"]), flush=True)


def _line(e: dict) -> str:
    var = np.asarray(e["var"])
    rec, mc = np.mean(e["recall"]), np.mean(e["mc_recall"])
    rate = e["rate"]
    cover = sum(lo <= rate <= hi for _, lo, hi in e["realised"])
    below = sum(hi < rate for _, _, hi in e["realised"])
    return (
        f"| {e['problem']} | {e['data_seed']} | {len(var)} | {e['screened']} | "
        f"{var.mean():.2f} [{var.max():.2f}] | {rec:.4f} ({rec / mc:.1f}x) | "
        f"{cover} of {len(e['realised'])} ({below} below) |"
    )


def table() -> None:
    results = json.loads(OUT.read_text())
    lines = [
        "# The shipped default estimate on held-out instances",
        "",
        "`docs/suite/heldout_default.py` (its docstring says how): BAMS with the defaults "
        "as shipped on every suite problem generated again with another data seed. "
        "screened: seeds where `--screen auto` screened. var / uniform: the default "
        "design's variance over a uniform Poisson design's of K level-0 runs, mean [max] "
        "over seeds. recall: failures in hand after the estimate over all failures (x: "
        "over plain MC's, same seeds). realised: the one estimate each run computed through "
        "`estimate --plan` ... `estimate`, whose 90% interval held the true rate (wholly "
        "below it).",
        "",
        "| problem | data seed | seeds | screened | var / uniform | recall (x MC) | realised "
        "interval holds the rate |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for key in sorted(results, key=lambda k: (PROBLEMS.index(k.split("/")[1]), k)):
        lines.append(_line(results[key]))
    lines += ["", NOTES.replace("\n", " ")]
    (HERE / "heldout_default.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str]) -> None:
    if argv[:1] == ["table"]:
        table()
        return
    if argv[:1] != ["run"] or len(argv) < 2:
        sys.exit(__doc__)
    seeds = 5
    if "--seeds" in argv:
        i = argv.index("--seeds")
        seeds = int(argv[i + 1])
        argv = argv[:i] + argv[i + 2 :]
    run(int(argv[1]), tuple(argv[2:]) or PROBLEMS, seeds)


if __name__ == "__main__":
    main(sys.argv[1:])
