"""The prior on lam where the fitted cheap level does not track level 0.

    .venv/bin/bams-cli benchmark --protocol suite --seeds 10 --strategies bams,mcm-gp \\
        --save-arrays --out /tmp/suite-arrays                        # the suite's runs
    .venv/bin/python docs/suite/heldout_estimate.py run 1 weak_cheap digits rare_regions \\
        --arrays /tmp/heldout-arrays                                 # and with 2
    .venv/bin/python docs/suite/fresh_problems.py run /tmp/fresh ...  # its docstring
    .venv/bin/python docs/suite/weak_cheap_prior.py run --suite /tmp/suite-arrays \\
        --heldout /tmp/heldout-arrays --fresh /tmp/fresh [--trials 300]
    .venv/bin/python docs/suite/weak_cheap_prior.py table

``estimate --plan`` takes the prior on lam (the share of failure mass p_n does not explain,
``core.design``) from the fitted model (``core.design.risk_prior``): Beta(0.5, 1) where
the cheap level tracks level 0 (discrepancy sd under ``defaults.SCREEN_HINT_DISCREPANCY``
of the level-0 signal's, where ``--screen auto`` screens), and
``defaults.RISK_MIX_PRIOR_WEAK_CHEAP`` elsewhere. This measures the staged design (the
default where auto does not screen) under Beta(0.5, 1), Beta(1, 1) and Beta(1, 0.5) on
every run whose model is above the threshold, drawn ``--trials`` times from the truth
(``core.evaluate.staged_trials``, each later stage keeping stage 1's p_n):

* the suite's saved runs (both GP strategies), each run's discrepancy from its last fit
  (``results.json``'s ``hyperparameters_final``);
* held-out instances of the suite's weak-model problems (``heldout_estimate.py run
  --arrays``: another data seed); their arrays keep no fit, so every run is counted: auto
  screened none of them (docs/suite/heldout_default.md);
* the three problems written after the defaults (``fresh_problems.py``), from the
  workspaces kept after batch 3, each run's discrepancy from its model.json.

Lines accumulate in docs/suite/weak_cheap_prior.jsonl; ``table`` writes the .md.
"""

from __future__ import annotations

import json
import sys
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
LINES = HERE / "weak_cheap_prior.jsonl"
PRIORS = ((0.5, 1.0), (1.0, 1.0), (1.0, 0.5))
SUITE = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")


def _ratio(hp: dict[str, Any] | None) -> float | None:
    from bams_cli.pipeline.screening import cheap_level_discrepancy

    return cheap_level_discrepancy({"hyperparameters": hp}) if hp else None


def _suite_runs(folder: Path) -> list[dict[str, Any]]:
    runs = []
    for problem in SUITE:
        z = np.load(folder / problem / "runs.npz")
        fail = z["f0"] <= float(z["gamma"])
        doc = json.loads((folder / problem / "results.json").read_text())
        for strategy in ("bams", "mcm-gp"):
            entry = doc.get(strategy)
            if not entry:
                continue
            for seed, hp in zip(entry["seed_values"], entry["hyperparameters_final"], strict=True):
                runs.append(
                    {
                        "source": "suite", "problem": problem, "strategy": strategy,
                        "seed": int(seed), "ratio": _ratio(hp), "fail": fail, "K": float(z["K"]),
                        "p": z[f"{strategy}-{seed}-p"], "known": z[f"{strategy}-{seed}-known"],
                    }
                )  # fmt: skip
    return runs


def _heldout_runs(folder: Path) -> list[dict[str, Any]]:
    runs = []
    for f in sorted(folder.glob("*.npz")):
        data_seed, problem = f.stem.split("-", 1)
        z = np.load(f)
        seeds = sorted({int(k.split("-")[0]) for k in z.files if k.endswith("-p")})
        for seed in seeds:
            runs.append(
                {
                    "source": f"held out, data seed {data_seed}", "problem": problem,
                    "strategy": "bams", "seed": seed, "ratio": None, "fail": z["fail"],
                    "K": float(z["K"]), "p": z[f"{seed}-p"], "known": z[f"{seed}-known"],
                }
            )  # fmt: skip
    return runs


def _fresh_runs(out: Path) -> list[dict[str, Any]]:
    import polars as pl

    sys.path.insert(0, str(HERE))
    import fresh_problems as FP

    runs = []
    for problem in ("cancer", "blind", "ties"):
        truth = pl.read_parquet(out / problem / "truth.parquet")
        gamma = float((out / problem / "gamma").read_text())
        for path in sorted((out / "runs").glob(f"{problem}-s*.estimate.json")):
            ws = path.with_name(path.name.removesuffix(".estimate.json"))
            ids = pl.read_parquet(ws / "segments.parquet", columns=["segment_id"])["segment_id"]
            p = pl.read_parquet(ws / "history" / "scores-after-batch-0003.parquet")["p_0"]
            obs = pl.read_parquet(ws / "observations.parquet")
            before = obs.filter(
                (pl.col("fidelity") == 0) & pl.col("batch").is_not_null() & (pl.col("batch") <= 3)
            )
            model = json.loads(path.with_name(f"{ws.name}.model-after-batch-3.json").read_text())
            value = ids.to_frame().join(truth, on="segment_id", how="left")["value_0"]
            runs.append(
                {
                    "source": "fresh", "problem": problem, "strategy": "bams",
                    "seed": int(ws.name.rsplit("-s", 1)[1]),
                    "ratio": _ratio(model.get("hyperparameters")),
                    "fail": value.to_numpy() <= gamma,
                    "K": FP._series_K(ws, json.loads(path.read_text())),
                    "p": p.to_numpy(), "known": ids.is_in(before["segment_id"].implode()).to_numpy(),
                }
            )  # fmt: skip
    return runs


def _trial(args: tuple[dict[str, Any], tuple[float, float], int]) -> dict[str, Any]:
    from bams_cli.core.evaluate import staged_trials

    run, prior, trials = args
    warnings.simplefilter("ignore")
    t = staged_trials(
        run["p"], run["fail"], K=run["K"], known=run["known"], prior=prior, n_trials=trials,
        rng=np.random.default_rng(run["seed"]),
    )  # fmt: skip
    return {
        **{k: run[k] for k in ("source", "problem", "strategy", "seed", "ratio")},
        "prior": list(prior), "trials": trials, "var_ratio": float(t.var / t.var_uniform),
        "coverage": t.coverage, "below": t.below, "above": t.above,
        "width": float(np.mean(t.ci_high - t.ci_low) / t.rate),
        "recall": float(t.recall.mean()),
    }  # fmt: skip


def run(suite: Path | None, heldout: Path | None, fresh: Path | None, trials: int) -> None:
    from bams_cli import defaults

    runs = [
        *(_suite_runs(suite) if suite else []),
        *(_heldout_runs(heldout) if heldout else []),
        *(_fresh_runs(fresh) if fresh else []),
    ]
    # The runs the weak-cheap prior applies to (held-out runs: no fit kept, all counted).
    runs = [r for r in runs if r["ratio"] is None or r["ratio"] >= defaults.SCREEN_HINT_DISCREPANCY]
    jobs = [(r, pr, trials) for r in runs for pr in PRIORS]
    with ProcessPoolExecutor(2) as pool, LINES.open("w") as fh:
        for row in pool.map(_trial, jobs):
            fh.write(json.dumps(row) + "\n")
    print(f"{len(runs)} runs x {len(PRIORS)} priors -> {LINES}")


def table() -> None:
    rows = [json.loads(s) for s in LINES.read_text().splitlines()]
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["source"], r["problem"], r["strategy"]), []).append(r)
    head = " | ".join(f"Beta({a:g}, {b:g})" for a, b in PRIORS)
    lines = [
        "# The prior on lam where the cheap level does not track level 0",
        "",
        "`docs/suite/weak_cheap_prior.py` (its docstring says how). The staged design drawn "
        f"{rows[0]['trials']} times per run from the truth under three priors on lam, on every "
        "run whose fitted cheap-level discrepancy sd is at least "
        "`defaults.SCREEN_HINT_DISCREPANCY` (0.3) of its level-0 signal's (held out: every run; "
        "auto screened none of them). Beta(0.5, 1) is the prior where the cheap level tracks "
        "level 0, and was the only one before 2026-11-28; Beta(1, 0.5) is "
        "`defaults.RISK_MIX_PRIOR_WEAK_CHEAP`. var: the design's variance over a uniform "
        "Poisson design's of the same K, mean [max] over runs; coverage of the 90% interval, "
        "and the shares of intervals wholly below / above the rate; width over the rate.",
        "",
        f"| source | problem | strategy | runs | var / uniform: {head} | coverage | "
        "below / above | width / rate |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    worst = {tuple(pr): 0.0 for pr in PRIORS}
    for (source, problem, strategy), rs in groups.items():
        by = {tuple(pr): [r for r in rs if tuple(r["prior"]) == pr] for pr in PRIORS}
        n = len(by[PRIORS[0]])
        var = []
        for pr in PRIORS:
            v = np.array([r["var_ratio"] for r in by[pr]])
            worst[pr] = max(worst[pr], float(v.max()))
            var.append(f"{v.mean():.3f} [{v.max():.3f}]")

        def each(key: str, fmt: str, rs_by: dict = by) -> str:
            return " / ".join(fmt.format(np.mean([r[key] for r in rs_by[pr]])) for pr in PRIORS)

        below_above = " ; ".join(
            f"{np.mean([r['below'] for r in by[pr]]):.3f} / {np.mean([r['above'] for r in by[pr]]):.3f}"
            for pr in PRIORS
        )
        lines.append(
            f"| {source} | {problem} | {strategy} | {n} | {' | '.join(var)} | "
            f"{each('coverage', '{:.3f}')} | {below_above} | {each('width', '{:.2f}')} |"
        )
    lines += [
        "",
        "Worst run, all sources: "
        + ", ".join(f"Beta({a:g}, {b:g}) {worst[(a, b)]:.3f}" for a, b in PRIORS)
        + ". Coverage, below / above and width list the three priors in the order above.",
        "",
        NOTES,
    ]
    (HERE / "weak_cheap_prior.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


#: What the table shows, as measured when it was made.
NOTES = """Measured 2026-11-27 (23:05; 38 s on 2 cores) on the suite's saved runs (the
benchmark of 2026-11-27 17:50, docs/reproduction/suite before this change), held-out
instances run afresh (`heldout_estimate.py run 1|2 weak_cheap digits rare_regions
--arrays`) and the fresh problems' kept workspaces (docs/suite/fresh_problems.md). No run
of toy2d, av_like, gap_sim or ties is above the threshold; of blind, the one run auto did
not screen.

- Under Beta(0.5, 1), the prior before, the worst run had 1.16 of uniform's variance on
  the suite (digits, rare_regions), 1.22 on held-out rare_regions (issue 12's bound is
  1.2) and 1.19 on cancer. Under Beta(1, 0.5) the worst run of every source is at most
  1.09 (suite 1.07, held out 1.08, cancer 1.09), and the mean falls on every problem but
  weak_cheap's held-out instances (0.84 -> 0.87, 0.85 -> 0.87), where the model ranks a
  little and stage 1 finds about 7 failures to learn from.
- Coverage, the misses on each side (none below on digits and rare_regions, about 3% on
  weak_cheap and cancer under every prior) and the width are the same under the three
  priors to within the draws' noise: the interval's allowance sits at lam's 0.9
  quantile, near uniform risk already under Beta(0.5, 1) (0.80; 0.98 under Beta(1, 0.5)).
- The price is paid where a model above the threshold ranks well: blind's unscreened run
  (a cheap level blind to one failure mode) 0.26 -> 0.36 of uniform's variance. Where the
  cheap level tracks level 0 (toy2d, av_like, gap_sim, ties, blind's other runs) the prior
  is Beta(0.5, 1) as before, and the screen is the default there.
- Beta(1, 1) lies between the two everywhere (worst 1.13).
- Through the CLI, as a study runs it (`fresh_problems.py make /tmp/s4/fresh2` and `run
  /tmp/s4/fresh2 cancer 0 1 2 3 4 5 6 7` at 0c448d3, 2026-11-27 23:43; the same data):
  every cancer run planned both stages under Beta(1, 0.5) (`model_check.prior`), all 8
  reported intervals held the true rate 0.0510 (at 42801af, under Beta(0.5, 1): 7 of 8,
  one below), mean p_hat 0.90 of the rate; the runs' staged designs drawn 1,000 times
  from the truth had 0.90 [1.08] of uniform's variance (0.91 [1.19]) and covered 0.938
  (lowest run 0.926), 3.0% of intervals below and 3.2% above; recall 1.29x plain MC's
  (1.4x), the price of trusting p_n less."""


def main(argv: list[str]) -> None:
    if argv[:1] == ["table"]:
        table()
        return
    if argv[:1] != ["run"]:
        raise SystemExit(__doc__)
    args = argv[1:]

    def opt(name: str) -> Path | None:
        return Path(args[args.index(name) + 1]) if name in args else None

    trials = int(args[args.index("--trials") + 1]) if "--trials" in args else 300
    run(opt("--suite"), opt("--heldout"), opt("--fresh"), trials)


if __name__ == "__main__":
    main(sys.argv[1:])
