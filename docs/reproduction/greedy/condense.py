"""Condense four ``bams-cli benchmark`` runs (exact and approximate greedy on two protocols)
into this folder's results.json and the table of its README.

    .venv/bin/python docs/reproduction/greedy/condense.py DIR

DIR holds the runs' ``--out`` folders, named ``toy2d-exact``, ``toy2d-approximate``,
``av20k-exact`` and ``av20k-approximate`` (the commands are in README.md beside this file).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

RUNS = {"toy2d": "toy2d (N 20,000)", "av20k": "av_like (N 20,000)"}
GREEDY = ("exact", "approximate")
STRATEGIES = ("bams", "bas")
KEEP = ("recall", "recall_se", "rv", "rv_se", "per_seed_recall", "per_seed_rv",
        "picks_per_level", "seconds_per_run")  # fmt: skip


def main(folder: Path) -> None:
    out: dict[str, dict] = {}
    rows = []
    for run, label in RUNS.items():
        res = {g: json.loads((folder / f"{run}-{g}" / "results.json").read_text()) for g in GREEDY}
        for g, r in res.items():
            out[f"{run}-{g}"] = {
                "command": r["command"],
                "wall_seconds": r["wall_seconds"],
                "setup": {
                    k: r["setup"][k] for k in ("pool_size", "greedy", "seeds", "clusters", "K")
                },
                **{s: {k: r[s][k] for k in KEEP} for s in STRATEGIES},
            }
        for s in STRATEGIES:
            for g in GREEDY:
                x = res[g][s]
                rows.append(
                    f"| {label} | {s.upper()} | {g} | {x['recall']:.4f} ± {x['recall_se']:.4f} | "
                    f"{x['rv']:.3f} ± {x['rv_se']:.3f} | {x['seconds_per_run']['select']:.1f} s |"
                )
            a, b = (res[g][s] for g in GREEDY)
            diff = [
                round(p - q, 4)
                for p, q in zip(a["per_seed_recall"], b["per_seed_recall"], strict=True)
            ]
            same = a["picks_per_level"] == b["picks_per_level"]
            print(f"{label} {s}: same picks per level in every seed: {same}; "
                  f"per-seed recall, exact minus approximate: {diff}")  # fmt: skip
    here = Path(__file__).parent
    (here / "results.json").write_text(json.dumps(out, indent=1) + "\n")
    print("| problem | strategy | greedy | recall | 100 x RV | select |")
    print("| --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
