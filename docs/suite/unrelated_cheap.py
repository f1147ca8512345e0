"""A cheap level that says little or nothing of level 0: what ``--screen auto`` costs there.

    .venv/bin/python docs/suite/fresh_problems.py make /tmp/fresh
    .venv/bin/python docs/suite/unrelated_cheap.py make /tmp/fresh /tmp/unrelated
    .venv/bin/python docs/suite/fresh_problems.py run /tmp/unrelated classif_perm 0 1 2 3
    ... (classif_c30, blind_perm, blind_c30 alike)
    .venv/bin/python docs/suite/unrelated_cheap.py table /tmp/unrelated [--trials 10]

Since 2026-11-30 ``--screen auto`` screens every study that has a cheap level. Every
problem measured until then (the suite's six, fresh_problems.py's nine) had a cheap level
that ranks level 0's failures better than chance, at least in its lowest tail. This script
builds two problems whose cheap level does not: fresh_problems' ``classif`` and ``blind``
(their embeddings and level 0 as they are) with the cheap level replaced by

* ``perm``: a random permutation of f0 (the same values, unrelated to each segment);
* ``c30``: a Gaussian copy of f0 at correlation 0.3 (mean + 0.3 (f0 - mean) + 0.95 sd e).

They are run through the CLI as fresh_problems.py runs its problems (``run``: three
discovery batches, then the default estimate, no truth given to the tool). ``table``
reads each run's workspace as it stood after batch 3 and draws from the truth:

* the screened design ``--screen auto`` plans (``benchmark.screen_default``, ``--trials``
  screens, each refitted on its true cheap values);
* the staged design ``--screen off`` would plan (``core.evaluate.staged_trials``, 1,000
  draws, its prior and open leads as ``estimate --plan`` takes them);
* the model-free screen of the same share that confirms its lowest cheap results
  (``screen_frontier.design``, exact): what a screen of that kind costs whatever the model.

It also shows what the study could have seen before the screen: its pairs (segments with a
level-0 and a cheap result) and their rank correlation, and the fitted cheap level's
discrepancy over level 0's signal (``pipeline.screening.cheap_level_discrepancy``).

Writes ``unrelated_cheap.md`` and ``unrelated_cheap.json`` beside this file.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

BASES = ("classif", "blind")
VARIANTS = ("perm", "c30")
DATA_SEED = 5


#: What the table shows, as measured when it was made.
NOTES = """
Measured 2026-11-30: runs 04:00-04:20 at 00331eb (`fresh_problems.py run`, seeds 0-3),
table 04:25-04:32 with 6 screens per run (`table /tmp/s20/fresh --trials 6`).
`--screen auto` screened all 16 runs.

- A cheap level unrelated to level 0 (perm): the screened design had 1.76-2.62 times a
  uniform design's variance on classif (mean 2.18) and 1.59-2.37 on blind (mean 2.01);
  the staged design that `--screen off` plans had 0.96-1.05 and 0.68-0.95. Model-free, a
  screen of 0.3 of K that confirms its lowest 0.5 K2 cheap results costs 2.2-2.4 times
  uniform's here: its leads are a random share of S1 taken at pi2 = 1, which starves the
  rest of S1 (closed form (K/A)(1 + (A - L)(A - K2)/(A (K2 - L))), A = |S1|, L the
  leads; tests/test_screen_frontier.py). Without leads it would cost 1/(1 - 0.3) = 1.43,
  the cheap runs' share of K.
- A cheap level at correlation 0.3 (c30): the screen still pays on classif (0.86-1.13,
  recall 1.3x-2.1x plain MC against the staged design's 1.02-1.03 and 0.8x-0.9x) and
  costs variance on blind (0.83-1.26 against 0.71-0.93, at 1.8x-4.9x recall against
  1.1x-3.1x).
- The realised intervals: all 8 perm runs held the rate (p_hat 0.16-2.19 of it, wide); 7
  of 8 c30 runs did, classif_c30 seed 2 lay above it (p_hat 3.89 of the rate).
- The whole estimate path drawn 12 times from seed 0's workspace of each perm problem
  (`fresh_problems.py repeat /tmp/s20/fresh PROBLEM 0 12`, 04:38-04:46 at 1ef5a58; each
  draw screens, refits, confirms and estimates as a study does): the unbiased sum came to
  1.19 ± 0.17 of the rate on blind_perm and 1.09 ± 0.26 on classif_perm; 11 of 12
  intervals held the rate on each, one lay above it, none below; median width 2.4 and 2.9
  times the rate. What the unrelated level costs is the interval's width, not its honesty.
- Nothing the study holds before the screen tells these apart from the fresh problems
  where the screen pays. After batch 3 each run had 5-10 pairs (a level-0 and a cheap
  result on one segment); their Spearman rho was -0.70 to 0.43 on perm and -0.38 to 0.90
  on c30, against 0.00 to 0.85 on classif's own cheap level (fresh_problems.py, where the
  screen took the design from 1.12 to 1.01 of uniform's variance and recall from 1.1x to
  2.1x). The fitted discrepancy over level 0's signal (the ratio `--screen auto` used to
  gate on, 0.3) was 0.99-4.80 on perm, 0.65-1.47 on c30, 0.43-1.78 on classif and
  0.72-3.85 on cancer: an additive discrepancy sees an unrelated cheap level of the same
  spread as one whose differences have sd sqrt(2) of level 0's, barely more than a weak
  one's.

Not built: evidence before the screen commits. Stage 1 of the staged estimate, run
unscreened with a cheap run on each of its own sampled segments (c1 K/3, 3% of K at a
cost of 0.1), would give K/3 pairs with their level-0 failures, enough to see whether the
lowest cheap results fail more often than the rest before the later stages screen. Until
then a study that knows its cheap level does not follow level 0 should plan with
`--screen off`; the plan's note says so.
"""


def cheap_variant(f0: np.ndarray, kind: str, rng: np.random.Generator) -> np.ndarray:
    """The variant's cheap level from level 0's values (module docstring)."""
    if kind == "perm":
        return rng.permutation(f0)
    if kind == "c30":
        z = rng.standard_normal(f0.size)
        return f0.mean() + 0.3 * (f0 - f0.mean()) + np.sqrt(1 - 0.3**2) * f0.std() * z
    raise ValueError(f"unknown variant {kind!r}; expected one of {VARIANTS}")


def make(fresh: Path, out: Path) -> None:
    """The four variants from fresh_problems.py's ``make`` output in ``fresh``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for base in BASES:
        rng = np.random.default_rng(DATA_SEED)
        t = pq.read_table(fresh / base / "truth.parquet")
        f0 = t.column("value_0").to_numpy()
        gamma = float((fresh / base / "gamma").read_text())
        for kind in VARIANTS:
            f1 = cheap_variant(f0, kind, rng)
            d = out / f"{base}_{kind}"
            d.mkdir(parents=True, exist_ok=True)
            shutil.copy(fresh / base / "segments.parquet", d / "segments.parquet")
            (d / "gamma").write_text(repr(gamma))
            table = {"segment_id": t.column("segment_id"), "value_0": f0, "value_1": f1}
            pq.write_table(pa.table(table), d / "truth.parquet")
            fail = f0 <= gamma
            print(
                f"{d.name}: rate {fail.mean():.4f}, corr(f0, f1) {np.corrcoef(f0, f1)[0, 1]:.2f}, "
                f"cheap level sees {np.mean(f1[fail] <= gamma):.2f} of the failures"
            )


def _pairs(ws: Path) -> tuple[int, float]:
    """(segments with a level-0 and a cheap result, Spearman's rho of their means)."""
    import polars as pl
    from scipy.stats import spearmanr

    obs = pl.read_parquet(ws / "observations.parquet")
    mean = {
        lv: obs.filter(pl.col("fidelity") == lv)
        .group_by("segment_id")
        .agg(pl.col("value").mean().alias(f"y{lv}"))
        for lv in (0, 1)
    }
    both = mean[0].join(mean[1], on="segment_id")
    if both.height < 3:
        return both.height, float("nan")
    return both.height, float(spearmanr(both["y0"], both["y1"])[0])


def evaluate(out: Path, problem: str, trials: int) -> list[dict]:
    """fresh_problems.py's evaluation of each run (the screened design at ``trials``
    screens, the staged one, the realised interval), with the model-free screen and what
    the study could see before the screen beside it."""
    import polars as pl
    import screen_frontier as sf
    from fresh_problems import _evaluate

    from bams_cli import benchmark, defaults
    from bams_cli.pipeline.screening import cheap_level_discrepancy

    truth = pl.read_parquet(out / problem / "truth.parquet")
    f0, f1 = truth["value_0"].to_numpy(), truth["value_1"].to_numpy()
    gamma = float((out / problem / "gamma").read_text())
    benchmark.SCREEN_TRIALS = trials  # read by benchmark.screen_default at each call
    s = defaults.SCREEN_HINT_SHARE
    rows = []
    for r in _evaluate(out, problem)["runs"]:
        kept = out / "runs" / f"{r['run']}.after-batch-3"
        free = sf._at_quantile(
            f0, f1, gamma, sf.FRESH_COST, r["K"], s,
            defaults.SCREEN_LEAD_SHARE * (1 - s) * sf.FRESH_COST / s,
        )  # fmt: skip
        n_pairs, rho = _pairs(kept)
        screened = r["screened"]
        rows.append(
            {
                "run": r["run"], "K": r["K"], "pairs": n_pairs, "pairs_spearman": rho,
                "fitted_discrepancy_ratio": cheap_level_discrepancy(
                    json.loads((kept / "model.json").read_text())
                ),
                "screened": screened,
                "screen_var": r["design_var_over_uniform"] if screened else None,
                "screen_recall_over_mc": r["recall_over_mc"] if screened else None,
                "staged_var": r["staged_var_over_uniform"],
                "staged_coverage": r["staged_coverage"],
                "staged_recall_over_mc": r["staged_recall_over_mc"],
                "model_free_var": free["var"] if free else None,
                "run_p_hat_over_rate": r["p_hat_over_rate"],
                "run_covers": bool(r["covers"]),
            }
        )  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    return rows


def _f(v: float | None, fmt: str = ".2f") -> str:
    return "-" if v is None or v != v else format(v, fmt)


def table(out: Path, trials: int) -> None:
    rows = []
    for base in BASES:
        for kind in VARIANTS:
            if (out / f"{base}_{kind}").exists():
                rows += evaluate(out, f"{base}_{kind}", trials)
    (HERE / "unrelated_cheap.json").write_text(json.dumps(rows, indent=1) + "\n")
    render(rows)


def render(rows: list[dict]) -> None:
    """unrelated_cheap.md from the rows (``render`` alone: from unrelated_cheap.json)."""
    lines = [
        "# A cheap level that says little or nothing of level 0",
        "",
        "`docs/suite/unrelated_cheap.py` (its docstring says how the problems are made and "
        "what each column is). Variance over a uniform Poisson design's of the same K, "
        "drawn from the truth; recall over plain MC's at the same cost.",
        "",
        "| run | pairs after batch 3 | their Spearman rho | fitted discrepancy / signal | "
        "screened (auto) | screened design: var / uniform | recall / MC | staged design "
        "(--screen off): var / uniform | coverage | recall / MC | model-free screen: "
        "var / uniform | run: p_hat / rate | run: interval holds the rate |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['pairs']} | {_f(r['pairs_spearman'])} | "
            f"{_f(r['fitted_discrepancy_ratio'])} | {'yes' if r['screened'] else 'no'} | "
            f"{_f(r['screen_var'])} | {_f(r['screen_recall_over_mc'], '.1f')}x | "
            f"{_f(r['staged_var'])} | {_f(r['staged_coverage'], '.3f')} | "
            f"{_f(r['staged_recall_over_mc'], '.1f')}x | {_f(r['model_free_var'])} | "
            f"{_f(r['run_p_hat_over_rate'])} | {'yes' if r['run_covers'] else 'no'} |"
        )
    lines += ["", *NOTES.strip().split("\n")]
    (HERE / "unrelated_cheap.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv: list[str]) -> None:
    if len(argv) >= 3 and argv[0] == "make":
        make(Path(argv[1]), Path(argv[2]))
    elif argv[:1] == ["render"]:
        render(json.loads((HERE / "unrelated_cheap.json").read_text()))
    elif len(argv) >= 2 and argv[0] == "table":
        trials = int(argv[argv.index("--trials") + 1]) if "--trials" in argv else 10
        table(Path(argv[1]), trials)
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
