"""The default estimate design on fresh realisations of the suite's problems.

    .venv/bin/python docs/suite/heldout_estimate.py run DATA_SEED [PROBLEM ...] [--arrays DIR]
    .venv/bin/python docs/suite/heldout_estimate.py retrial ARRAYS_DIR       # designs again
    .venv/bin/python docs/suite/heldout_estimate.py fixed-lam ARRAYS_DIR PROBLEM
    .venv/bin/python docs/suite/heldout_estimate.py table

The estimate's defaults (the prior on lam, the calibration shapes, the stage-1 share;
``core.design``, docs/suite/risk_prior.md) were chosen on the suite's problems, generated
with data seed 0. Here each problem is generated again with another data seed (another
latent map, failure regions, bias; digits: another split and cheap model) and BAMS runs the
suite's protocol on it, seeds 0-9, with the defaults as shipped. For every run
``core.evaluate.staged_trials`` draws the default staged design 100 times from the truth
(as ``docs/suite/estimate_design.py`` does on the suite) and records the design's variance
against a uniform Poisson design of the same expected size, and the default 90% interval's
coverage, misses below and above. Issue 12 asks for at most 1.2x uniform's variance on
every problem and at least 0.88 coverage; these problems were not used to choose anything.

Results accumulate in docs/suite/heldout_estimate.json (one entry per data seed and
problem); ``table`` writes docs/suite/heldout_estimate.md from it.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import evidence as E
import numpy as np

from bams_cli import benchmark as B
from bams_cli.settings import Settings

HERE = Path(__file__).resolve().parent
OUT = HERE / "heldout_estimate.json"
PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
TRIALS = 100


#: What the table says, as measured when it was made (2026-11-25, data seeds 1 and 2).
NOTES = """What it says (2026-11-25, at 318464e): the default design kept within 1.2x of uniform's
variance on 119 of 120 runs (one rare_regions seed at 1.222, data seed 2) and covered the
true rate in 0.933-0.986 of the draws, wholly below it in at most 3.8% (weak_cheap), on
problems none of its defaults were chosen on. av_like's 1/5 (0.184 on the suite's
instance) did not carry over: 0.309 and 0.370. These instances' models leave failures at a
relative risk of 0.01-0.5, and no fixed trust reaches 1/5 on them:
`heldout_estimate.py fixed-lam /tmp/heldout-arrays av_like` printed, mean [max] over seeds,
data seed 1: lam 0: 0.209 [0.685], 0.1: 0.256 [0.525], 0.2: 0.289 [0.547], 0.33: 0.324
[0.584], 0.5: 0.368 [0.631]; data seed 2: lam 0: 1.149 [8.564], 0.1: 0.319 [0.421], 0.2:
0.344 [0.434], 0.33: 0.375 [0.454], 0.5: 0.416 [0.499]. With the default design BAMS's
recall is 1.2-1.7x uniform's on weak_cheap and digits and 1.0x and 2.4x on rare_regions;
with p^alpha 1.4-4.3x."""


def _trials(p: np.ndarray, fail: np.ndarray, known: np.ndarray, K: float, seed: int) -> dict:
    from bams_cli.core.evaluate import staged_trials

    warnings.simplefilter("ignore")
    r = staged_trials(p, fail, K=K, known=known, n_trials=TRIALS, rng=np.random.default_rng(seed))
    return {
        "seed": seed,
        "recall": _recall(p, fail, known, K),
        "recall_staged": float(r.recall.mean()),
        "ratio": r.var / r.var_uniform,
        "coverage": r.coverage,
        "below": r.below,
        "above": r.above,
        "lam": float(r.lam.mean()),
        "mean_p_hat": float(r.p_hat.mean() / r.rate),
    }


def _recall(p: np.ndarray, fail: np.ndarray, known: np.ndarray, K: float) -> float:
    """Expected share of the true failures in hand after the plan (the suite's recall: the
    single-stage p^alpha design's, exact; ``benchmark.design_stats``)."""
    recall, _ = B.design_stats(p, fail, K=K, known=known, **B.estimate_defaults())
    return float(recall)


def run(data_seed: int, problems: tuple[str, ...], arrays: Path | None = None) -> None:
    results = json.loads(OUT.read_text()) if OUT.exists() else {}
    for problem in problems:
        original = B.GENERATORS[problem]
        B.GENERATORS[problem] = lambda n, _seed, _g=original: _g(n, data_seed)
        t0 = time.perf_counter()
        try:
            proto = B.PROTOCOLS[problem]
            with tempfile.TemporaryDirectory(prefix="bams-heldout-estimate-") as tmp:
                # Not the committed sample data (data seed 0): a pool generated afresh.
                B.SAMPLE_DATA = Path(tmp) / "no-sample-data"
                data = B.prepare_data(proto, None, Path(tmp))
                f0 = B._column(data / "truth.parquet", "value_0").astype(np.float64)
                gamma = Settings.from_toml((data / "settings.toml").read_text()).gammas[0]
                fail = f0 <= gamma
                K = float(round(proto.k_factor * fail.sum()))
                specs = [B.RunSpec(problem, "bams", s, str(data), tmp, 0.5, 6, K) for s in E.SEEDS]
                with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
                    runs = list(pool.map(E._worker, specs, [{}] * len(specs), [{}] * len(specs)))
                    rows = list(
                        pool.map(
                            _trials,
                            [r["p"] for r in runs],
                            [fail] * len(runs),
                            [r["known"] for r in runs],
                            [K] * len(runs),
                            [r["seed"] for r in runs],
                        )
                    )
                if arrays is not None:
                    arrays.mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(
                        arrays / f"{data_seed}-{problem}.npz",
                        fail=fail,
                        K=K,
                        **{f"{r['seed']}-p": r["p"] for r in runs},
                        **{f"{r['seed']}-known": r["known"] for r in runs},
                    )
        finally:
            B.GENERATORS[problem] = original
        results[f"{data_seed}/{problem}"] = {
            "data_seed": data_seed,
            "problem": problem,
            "rate": float(fail.mean()),
            "K": K,
            "seconds": time.perf_counter() - t0,
            "runs": rows,
        }
        OUT.write_text(json.dumps(results, indent=1) + "\n")
        print(problem, data_seed, _line(results[f"{data_seed}/{problem}"]), flush=True)


def _line(entry: dict[str, Any]) -> str:
    rs = entry["runs"]
    ratio = np.array([r["ratio"] for r in rs])
    cov = np.mean([r["coverage"] for r in rs])
    below = np.mean([r["below"] for r in rs])
    above = np.mean([r["above"] for r in rs])
    proto = B.PROTOCOLS[entry["problem"]]
    uniform = (proto.m1 + proto.mb * (proto.n_batches - 1) + entry["K"]) / len_pool(entry)
    recall = ""
    for key in ("recall_staged", "recall"):
        rec = [r[key] for r in rs if key in r]
        recall += (
            f"{np.mean(rec):.3f} ± {np.std(rec, ddof=1) / np.sqrt(len(rec)):.3f} | "
            f"{np.mean(rec) / uniform:.1f}x"
            if len(rec) == len(rs)
            else "- | -"
        ) + (" | " if key == "recall_staged" else "")
    return (
        f"| {entry['problem']} | {entry['data_seed']} | {entry['rate']:.4f} | {entry['K']:.0f} | "
        f"{recall} | "
        f"{ratio.mean():.3f} [{ratio.max():.3f}] | {int((ratio <= 1.2).sum())}/{ratio.size} | "
        f"{cov:.3f} | {below:.3f} | {above:.3f} | "
        f"{np.mean([r['mean_p_hat'] for r in rs]):.3f} | {np.mean([r['lam'] for r in rs]):.2f} |"
    )


def len_pool(entry: dict[str, Any]) -> int:
    """N of the entry's pool (the protocol's default size; the rate is over it)."""
    return int(B.PROTOCOLS[entry["problem"]].default_n)


def retrial(arrays: Path) -> None:
    """Draw the designs again from the runs' saved arrays (``run --arrays``), without
    rerunning the loop: every entry whose arrays are there gets fresh rows."""
    results = json.loads(OUT.read_text())
    for key, entry in results.items():
        f = arrays / f"{key.replace('/', '-')}.npz"
        if not f.exists():
            continue
        z = np.load(f)
        seeds = [r["seed"] for r in entry["runs"]]
        with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
            entry["runs"] = list(
                pool.map(
                    _trials,
                    [z[f"{s}-p"] for s in seeds],
                    [z["fail"]] * len(seeds),
                    [z[f"{s}-known"] for s in seeds],
                    [float(z["K"])] * len(seeds),
                    seeds,
                )
            )
        print(_line(entry), flush=True)
    OUT.write_text(json.dumps(results, indent=1) + "\n")


def fixed_lam(
    arrays: Path, problem: str, lams: tuple[float, ...] = (0, 0.1, 0.2, 0.33, 0.5)
) -> None:
    """Variance over uniform's of a single-stage calibrated design at fixed lam (tau 1),
    mean [max] over seeds, per saved instance of ``problem``: how far any fixed trust in
    p_n gets on it (as ``risk_prior.py --fixed-lam`` on the suite)."""
    from bams_cli.core import design as dz

    warnings.simplefilter("ignore")
    for f in sorted(arrays.glob(f"*-{problem}.npz")):
        z = np.load(f)
        fail, K = z["fail"], float(z["K"])
        ratios = []
        for s in E.SEEDS:
            known, p = z[f"{s}-known"], z[f"{s}-p"]
            U = np.flatnonzero(~known)
            Ku = min(K, U.size)
            fu, u = fail[U], dz.relative_risk(p[U])
            v_u = fu.sum() * (U.size - Ku) / Ku
            row = []
            for lam in lams:
                pi = dz.calibrated_design(lam + (1.0 - lam) * u, K=Ku)
                row.append(float(((1.0 - pi[fu]) / pi[fu]).sum()) / v_u)
            ratios.append(row)
        mean, top = np.mean(ratios, axis=0), np.max(ratios, axis=0)
        print(
            f.stem,
            " / ".join(
                f"{a:g}: {m:.3f} [{t:.3f}]" for a, m, t in zip(lams, mean, top, strict=True)
            ),
        )


def table() -> None:
    results = json.loads(OUT.read_text())
    lines = [
        "# The default estimate design on problems it was not chosen on",
        "",
        "`docs/suite/heldout_estimate.py run DATA_SEED` (its docstring says how): each suite "
        "problem generated again with another data seed, BAMS over seeds 0-9 with the shipped "
        f"defaults, then {TRIALS} draws of the default staged design per run from the truth. "
        "var / uniform: the design's variance over a uniform Poisson design's of the same "
        "expected size, mean [max] over seeds, and the seeds at or under 1.2x; coverage of the "
        "default 90% interval over all draws, and the shares of intervals wholly below and "
        "wholly above the true rate; mean p_hat / rate; lam: the mean share of failure mass "
        "stage 2 left to uniform risk. recall: the expected share of the true failures in "
        "hand after the estimate, for the default (staged) design over the draws and for "
        "the single-stage p^alpha design, exact, as the suite's table counts them; each "
        "over uniform level-0 sampling's expectation at the same cost, (B + K) / N with B "
        "the discovery budget in level-0 runs.",
        "",
        "| problem | data seed | p | K | recall, default ± SE | / uniform "
        "| recall, p^alpha ± SE | / uniform | var / uniform "
        "| within 1.2x | coverage | below | above | mean p_hat / rate | lam |",
        "|" + " --- |" * 15,
    ]
    keys = sorted(results, key=lambda k: (PROBLEMS.index(k.split("/")[1]), int(k.split("/")[0])))
    lines += [_line(results[k]) for k in keys]
    lines += ["", NOTES]
    (HERE / "heldout_estimate.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    if sys.argv[1] == "run":
        args = sys.argv[3:]
        arrays = None
        if "--arrays" in args:  # keep each run's p_n and known stratum there
            i = args.index("--arrays")
            arrays = Path(args[i + 1])
            del args[i : i + 2]
        run(int(sys.argv[2]), tuple(args) or PROBLEMS, arrays)
    elif sys.argv[1] == "retrial":
        retrial(Path(sys.argv[2]))
    elif sys.argv[1] == "fixed-lam":
        fixed_lam(Path(sys.argv[2]), sys.argv[3])
    else:
        table()
