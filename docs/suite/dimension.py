"""How many PCA components the GP should see: BAMS on the suite problems at several dims.

    .venv/bin/python docs/suite/dimension.py run OUT rare_regions=12,rare_regions=24,gap_sim=auto --seeds 10
    .venv/bin/python docs/suite/dimension.py render OUT          # writes docs/suite/dimension.md
    .venv/bin/python docs/suite/dimension.py render docs/suite/dimension   # from the saved runs

``run`` runs ``bams-cli benchmark``'s suite protocol (``benchmark.run_benchmark``, the real
select, simulate, ingest-results and fit path; BAMS only, one worker) for each
``problem=dim`` given, the dimension a number or ``auto`` (``embed-reduce --dim auto``,
``core.reduce.choose_dim``), into OUT/PROBLEM-DIM/. ``render`` tabulates what the suite
table shows for each: recall, the fitted over the true discrepancy sd, level-0 picks per
batch and the GP's own rate over the true one (``benchmark.suite_rows``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from bams_cli import benchmark as B

HERE = Path(__file__).resolve().parent


def run(out: Path, spec: str, seeds: int) -> None:
    for item in spec.split(","):
        name, dim = item.split("=")
        reduce = {"method": "pca", "dim": dim if dim == "auto" else int(dim)}
        B.PROTOCOLS[name] = dataclasses.replace(B._suite_protocol(name), reduce=reduce)
        B.run_benchmark(
            name, seeds=seeds, quick=False, out_dir=out / f"{name}-{dim}", strategies=["bams"],
            level0_share=0.5, workers=1, progress=None,
        )  # fmt: skip
        print(f"{name} at {dim}: done", flush=True)


def render(out: Path) -> str:
    lines = [
        "# How many PCA components: BAMS on the suite at several dimensions",
        "",
        "`docs/suite/dimension.py` (its docstring says how): BAMS on each suite problem with "
        "the embedding reduced to the given number of PCA components, the protocol of "
        "`bams-cli benchmark --protocol suite` otherwise, seeds 0-9. Recall: the expected "
        "share of true failures in hand after the estimate plan (K = 2 p N), exact; beside it, "
        "uniform level-0 sampling's, (budget + K) / N, which is at or above the suite's "
        "measured plain MC (digits: 0.058). disc. fitted / true: the final model's level-1 "
        "discrepancy sd over the true sd, mean [range] and the seeds within a factor 2. "
        "auto is `embed-reduce --dim auto` (`core.reduce.choose_dim`).",
        "",
        "| problem | dim | recall ± SE | BAMS / uniform | disc. fitted / true (within 2x) "
        "| level-0 picks per batch | GP / p | uniform recall |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]

    def order(path: Path) -> tuple[int, int]:
        name, dim = path.stem.rsplit("-", 1)
        return (B.SUITE.index(name), int(dim) if dim.isdigit() else 999)

    # OUT/PROBLEM-DIM/results.json as ``run`` writes them, or PROBLEM-DIM.json copies of
    # them (docs/suite/dimension/, what dimension.md was rendered from).
    found = [p / "results.json" if p.is_dir() else p for p in out.iterdir()]
    for path in sorted(found, key=lambda p: order(p.parent if p.name == "results.json" else p)):
        folder = path.parent if path.name == "results.json" else path.with_suffix("")
        result = json.loads(path.read_text())
        row = B.suite_rows(result)["strategies"]["bams"]
        st = result["setup"]
        mc = (st["m1"] + (st["batches"] - 1) * st["mb"] + st["K"]) / st["pool_size"]
        lo, hi = row["discrepancy_sd_ratio_range"]
        # The dimension each run's model saw (auto's choice, or the number given).
        dims = sorted({len(h["lengthscales0"]) for h in result["bams"]["hyperparameters_final"]})
        given = folder.name.rsplit("-", 1)[1]
        dim = given if given != "auto" else f"auto ({', '.join(map(str, dims))})"
        lines.append(
            f"| {folder.name.rsplit('-', 1)[0]} | {dim} | {row['recall']:.3f} ± "
            f"{row['recall_se']:.3f} | {row['recall'] / mc:.1f}x | "
            f"{row['discrepancy_sd_ratio']:.2f} [{lo:.2f}, {hi:.2f}] "
            f"({row['discrepancy_within_2x']}/{st['seeds']}) | "
            f"{' / '.join(f'{v:.1f}' for v in row['level0_per_batch'])} | "
            f"{row['gp_rate_ratio']:.2f} | {mc:.4f} |"
        )
    lines += [
        "",
        "What it says (2026-11-25): how much variance a component carries says nothing of "
        "its bearing on failures. gap_sim's 16 columns drop 3.8x after component 5, and "
        "five components lost a factor the failures hang on (recall 0.041, against 0.21 "
        "at 8 and 0.28 at 12); rare_regions' 96 columns drop 3.8x after component 24, the "
        "latent's 24 factors, and twelve kept half of them (0.007, about uniform "
        "sampling's, against 0.018 at 24). So `--dim auto` never keeps fewer than 12 "
        "components (the default until then) and keeps more where the spectrum drops off "
        "a cliff past 12, within the first 32: 24 on rare_regions, 12 on the other "
        "three. Against the old default of 12 it changes only rare_regions; against the "
        "hand-picked dims the suite passed until then it gains on gap_sim (0.28 against "
        "0.21) and rare_regions and loses on weak_cheap (0.075 against 0.117 at 8, the "
        "latent's 7 factors plus one; its discrepancy within 2x on 7 seeds of 10, not 9) "
        "and, within one SE, on digits. No rule of the spectrum alone found weak_cheap's "
        "8: the cliff after 7 kept 7 (0.090).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    if argv[:1] == ["run"]:
        seeds = int(argv[argv.index("--seeds") + 1]) if "--seeds" in argv else 10
        run(Path(argv[1]), argv[2], seeds)
    elif argv[:1] == ["render"]:
        text = render(Path(argv[1]))
        (HERE / "dimension.md").write_text(text)
        print(text)
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
