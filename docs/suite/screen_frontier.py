"""How much recall a cheap-level screen can buy within issue 12's variance bound, from truth.

    .venv/bin/python docs/suite/screen_frontier.py run [--fresh FOLDER] [--out docs/suite]
    .venv/bin/python docs/suite/screen_frontier.py check

``recall_bound.py`` bounds the designs that rank by the discovery model's p_n. This script
bounds another class, one that needs no model at all: spend a share s of the estimate's
K on cheap runs of a uniform Poisson sample S1 (each segment with pi1 = s K / (c1 N), c1
the cheap run's cost), then run at level 0 every segment of S1 whose cheap value is at or
below a threshold t (a lead) and each other segment of S1 with probability pi2, the rest
of K paying for them. A segment's inclusion probability is pi1 (a lead) or pi1 pi2, so the
Horvitz-Thompson sum of the failures found is unbiased and, the phases' draws being
independent per segment, its variance is exactly

    sum over failures of (1 / pi - 1)

(``check`` draws the design 100,000 times on a small pool and compares). Recall is the
failures' mean pi (the estimate's own; discovery's 20 cost units add the same for every
design), over a uniform level-0 design's K / N; the variance is over that uniform
design's, F (N / K - 1). Since pi <= pi1, recall can never exceed s / c1 times uniform's.

With hindsight the threshold t is taken from the pool's own cheap values (a quantile q of
f1), which a study would read from S1's; the threshold and the share are searched on a grid
per problem (the frontier), or held fixed across problems (a rule, as a default must be).
Problems: the suite's six at data seed 0, K = 2 p N as in the suite, and, with
``--fresh``, ``fresh_problems.py``'s (made by its ``make``; cost 0.1, as its runs use;
veryrare's K at the tool's floor of 100).

Writes ``screen_frontier.json`` and ``screen_frontier.md`` to ``--out``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

SUITE = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
#: Issue 12's bound on the design's variance over a uniform design's.
RATIO = 1.2
#: Lead thresholds searched: quantiles of the pool's cheap values.
QUANTILES = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)
#: Screen shares of K searched.
SHARES = tuple(np.round(np.arange(0.05, 0.96, 0.05), 2))
#: Fixed rules shown across every problem: (share s, lead threshold as m times the rate
#: the study planned K for, K / 2N).
RULES = ((0.3, 2), (0.3, 4), (0.4, 4), (0.6, 8), (0.8, 8))
#: ... and the rule ``estimate --plan`` ships (``core.screen.screen_leads``), which needs no
#: rate: share s, leads the lowest h K2 of S1's cheap values (K2 = (1 - s) K), i.e. the
#: pool's lowest h (1 - s) c1 / s.
LEAD_RULES = ((0.3, 0.3), (0.3, 0.5), (0.3, 0.7), (0.4, 0.5))
FRESH_COST = 0.1
K_FLOOR = 100.0


def design(f0, f1, gamma: float, c1: float, K: float, share: float, t: float):
    """(recall over uniform's, variance over uniform's, pi2) of the screen at share s and
    threshold t, or None where the leads alone cost more than K."""
    N = f0.size
    fail = f0 <= gamma
    F = int(fail.sum())
    pi1 = min(1.0, share * K / (c1 * N))
    lead = f1 <= t
    L, NL = int(lead.sum()), int((~lead).sum())
    rest = K - N * pi1 * c1 - pi1 * L
    if rest <= 0.0 or F == 0:
        return None
    pi2 = min(1.0, rest / (pi1 * NL)) if NL else 1.0
    pi = np.where(lead, pi1, pi1 * pi2)
    var = float(np.sum(1.0 / pi[fail] - 1.0))
    uniform = F * (N / K - 1.0)
    return float(pi[fail].mean()) / (K / N), var / uniform, pi2


def grid(f0, f1, gamma, c1, K) -> dict:
    """(recall, var) of every (share, threshold quantile) of the search, once per problem
    (None where infeasible)."""
    cuts = {q: float(np.quantile(f1, q)) for q in QUANTILES}
    out = {}
    for s in SHARES:
        for q, t in cuts.items():
            r = design(f0, f1, gamma, c1, K, float(s), t)
            out[float(s), q] = None if r is None else (r[0], r[1])
    return out


def frontier(g: dict, ratio: float = RATIO, shares=SHARES):  # noqa: ANN001
    """The largest recall over the grid's (share, threshold) at variance <= ratio x
    uniform's, over ``shares``."""
    best = None
    for (s, q), r in g.items():
        if s in shares and r and r[1] <= ratio and (best is None or r[0] > best["recall"]):
            best = {"share": s, "q": q, "recall": r[0], "var": r[1]}
    return best


def least_variance(g: dict, share: float):
    """The least variance over the grid's thresholds at a fixed share, and the recall there."""
    out = None
    for (s, q), r in g.items():
        if s == share and r and (out is None or r[1] < out["var"]):
            out = {"q": q, "recall": r[0], "var": r[1]}
    return out


def _at_quantile(f0, f1, gamma, c1, K, share: float, q: float):  # noqa: ANN001
    """A fixed rule's (recall, var) as a dict, the threshold the pool's q-quantile of f1."""
    r = design(f0, f1, gamma, c1, K, share, float(np.quantile(f1, min(1.0, q))))
    return None if r is None else {"recall": r[0], "var": r[1]}


def problems(fresh: Path | None):
    from bams_cli.benchmark import GENERATORS, PROTOCOLS

    for name in SUITE:
        pool = GENERATORS[name](PROTOCOLS[name].default_n, 0)
        f0, f1 = pool.truth[:, 0], pool.truth[:, 1]
        K = 2.0 * float(np.sum(f0 <= pool.gamma))
        yield name, f0, f1, float(pool.gamma), float(pool.costs[1] / pool.costs[0]), K
    if fresh is None:
        return
    import pyarrow.parquet as pq

    for folder in sorted(p for p in fresh.iterdir() if (p / "truth.parquet").exists()):
        t = pq.read_table(folder / "truth.parquet")
        f0 = t.column("value_0").to_numpy()
        f1 = t.column("value_1").to_numpy()
        gamma = float((folder / "gamma").read_text())
        K = max(K_FLOOR, 2.0 * float(np.sum(f0 <= gamma)))
        yield folder.name, f0, f1, gamma, FRESH_COST, K


def run(fresh: Path | None, out: Path, command: str = "run") -> dict:
    t0 = time.time()
    rows = []
    for name, f0, f1, gamma, c1, K in problems(fresh):
        fail = f0 <= gamma
        g = grid(f0, f1, gamma, c1, K)
        row = {
            "problem": name,
            "suite": name in SUITE,
            "N": int(f0.size),
            "failures": int(fail.sum()),
            "K": K,
            "c1": c1,
            "seen": float(np.mean(f1[fail] <= gamma)),
            "frontier": frontier(g),
            "frontier_any_var": frontier(g, ratio=np.inf),
            "by_share": {str(x): least_variance(g, float(x)) for x in SHARES},
            "by_share_best": {str(x): frontier(g, shares=(float(x),)) for x in SHARES},
            # m times the rate K was planned for; h K2 of S1 (K2 = (1 - s) K).
            "rules": {
                f"{x}/{m}": _at_quantile(f0, f1, gamma, c1, K, x, m * K / (2 * f0.size))
                for x, m in RULES
            },
            "lead_rules": {
                f"{x}/{h}": _at_quantile(f0, f1, gamma, c1, K, x, h * (1 - x) * c1 / x)
                for x, h in LEAD_RULES
            },
        }
        rows.append(row)
    doc = {"rows": rows, "ratio": RATIO, "command": command, "seconds": round(time.time() - t0, 1)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "screen_frontier.json").write_text(json.dumps(doc, indent=1) + "\n")
    (out / "screen_frontier.md").write_text(table(doc))
    return doc


def _x(v) -> str:
    return "-" if v is None else f"{v['recall']:.1f}x / {v['var']:.2f}"


def _rv(v) -> str:
    return "-" if v is None else f"{v['recall']:.2f}x (var {v['var']:.2f})"


def _vr(v) -> str:
    return "-" if v is None else f"{v['var']:.2f} ({v['recall']:.2f}x)"


def _rule_table(rows: list[dict], key: str, rules, name: str) -> list[str]:  # noqa: ANN001
    """One row per problem, one column per (share, parameter) rule."""
    out = [
        "| problem | " + " | ".join(f"s {s}, {name} {v}" for s, v in rules) + " |",
        "| --- | " + " | ".join("---" for _ in rules) + " |",
    ]
    for r in rows:
        out.append(
            f"| {r['problem']} | " + " | ".join(_x(r[key][f"{s}/{v}"]) for s, v in rules) + " |"
        )
    return out


def _shows(by: dict) -> list[str]:
    """What the share table shows, read off it."""
    rare = by["rare_regions"]["by_share_best"]
    reach = [float(s) for s in rare if rare[s] and rare[s]["recall"] >= 5.0]
    lines = ["What it shows:", ""]
    if reach:
        s_r = min(reach)
        lines.append(
            f"- rare_regions reaches 5x a uniform design's recall within 1.2x its variance "
            f"only at a screen share of {s_r:.2f} or more ({rare[str(s_r)]['recall']:.2f}x "
            f"there): recall cannot pass s / c1 = s / {by['rare_regions']['c1']:.3g}."
        )
    else:
        s_r = None
        lines.append("- rare_regions does not reach 5x at any share within 1.2x the variance.")
    for name in ("weak_cheap", "digits"):
        ok = [float(s) for s, v in by[name]["by_share"].items() if v and v["var"] <= RATIO]
        if s_r is not None and ok:
            at = by[name]["by_share"].get(str(s_r))
            lines.append(
                f"- {name} stays within 1.2x uniform's variance at shares "
                f"{min(ok):.2f}-{max(ok):.2f} only; at {s_r:.2f} its least variance is "
                f"{'-' if at is None else format(at['var'], '.2f')}x."
            )
    return lines


def table(doc: dict) -> str:
    rows = doc["rows"]
    out = [
        "# What a cheap-level screen can buy, from each problem's truth",
        "",
        "`docs/suite/screen_frontier.py` (its docstring says how). A share s of the "
        "estimate's K buys cheap runs of a uniform sample S1; every segment of S1 whose "
        "cheap value is at or below a threshold (a lead) is run at level 0, the others of "
        "S1 with the probability the rest of K pays for. Recall: the failures' mean "
        "inclusion probability over a uniform level-0 design's (K / N), the estimate's "
        "own (discovery adds the same to every design); var: the exact Horvitz-Thompson "
        "variance over the uniform design's. No model is used; the threshold is a quantile "
        "of the pool's cheap values and, in the frontier, chosen with hindsight. Recall "
        "cannot exceed s / c1 (the screen's share over the cheap run's cost).",
        "",
        "| problem | N | failures | seen at level 1 | K | c1 | best recall at var <= 1.2x (share, threshold q, var) | best recall, any var |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        f, g = r["frontier"], r["frontier_any_var"]
        best = (
            "-"
            if f is None
            else (f"{f['recall']:.2f}x (s {f['share']:.2f}, q {f['q']}, var {f['var']:.2f})")
        )
        anyv = "-" if g is None else f"{g['recall']:.2f}x (s {g['share']:.2f}, var {g['var']:.2f})"
        out.append(
            f"| {r['problem']} | {r['N']:,} | {r['failures']} | {r['seen']:.0%} | {r['K']:.0f} "
            f"| {r['c1']:.3g} | {best} | {anyv} |"
        )
    by = {r["problem"]: r for r in rows}
    if {"rare_regions", "weak_cheap", "digits"} <= set(by):
        out += [
            "",
            "One share for every problem, as a default must be (a study cannot tell these "
            "three apart before its estimate: `screen_design.md`, signals). Per share: "
            "rare_regions' best recall over thresholds at var <= 1.2x (hindsight), and "
            "weak_cheap's and digits' least variance over thresholds (hindsight), with the "
            "recall there.",
            "",
            "| share s | rare_regions: best recall at var <= 1.2x | weak_cheap: least var (recall) | digits: least var (recall) |",
            "| --- | --- | --- | --- |",
        ]
        for s in SHARES:
            rare = by["rare_regions"]["by_share_best"][str(s)]
            w, d = by["weak_cheap"]["by_share"][str(s)], by["digits"]["by_share"][str(s)]
            out.append(f"| {s:.2f} | {_rv(rare)} | {_vr(w)} | {_vr(d)} |")
        out += ["", *_shows(by)]
    out += [
        "",
        "Fixed rules on every problem: share s, leads the segments of S1 whose cheap value "
        "lies in the pool's lowest m K / 2N (m times the rate K was planned for); recall "
        "over uniform's / var over uniform's ('-': the leads alone cost more than K).",
        "",
        *_rule_table(rows, "rules", RULES, "m"),
        "",
        "The rule `estimate --plan` ships (`core.screen.screen_leads`, no rate needed): "
        "share s, leads the lowest h K2 of S1's cheap values, K2 = (1 - s) K the level-0 "
        "runs left; the rest of K2 spread uniformly over S1 here (the tool spreads it by "
        "the refitted model). Worst variance over the problems where it is feasible:",
        "",
        *_rule_table(rows, "lead_rules", LEAD_RULES, "h"),
    ]
    worst = []
    for s, h in LEAD_RULES:
        vs = [r["lead_rules"][f"{s}/{h}"] for r in rows]
        vs = [v for v in vs if v]
        worst.append(f"{max(v['var'] for v in vs):.2f} / {min(v['recall'] for v in vs):.1f}x")
    out.append("| worst var / least recall | " + " | ".join(worst) + " |")
    out += [
        "",
        f"Command: `.venv/bin/python docs/suite/screen_frontier.py {doc['command']}` "
        f"({doc['seconds']} s; the fresh problems made by `fresh_problems.py make FOLDER`).",
    ]
    return "\n".join(out) + "\n"


def check(n: int = 400, draws: int = 100_000, seed: int = 1) -> tuple[float, float, float, float]:
    """The design drawn ``draws`` times on a small pool: mean and variance of the
    Horvitz-Thompson sum against the total and the exact formula."""
    rng = np.random.default_rng(seed)
    f0 = rng.standard_normal(n)
    f1 = f0 + 0.7 * rng.standard_normal(n)
    gamma, c1, K, share = -1.5, 0.1, 40.0, 0.3
    t = float(np.quantile(f1, 0.1))
    r = design(f0, f1, gamma, c1, K, share, t)
    assert r is not None
    pi1 = share * K / (c1 * n)
    pi2 = r[2]
    fail = f0 <= gamma
    lead = f1 <= t
    pi = np.where(lead, pi1, pi1 * pi2)
    s1 = rng.random((draws, n)) < pi1
    s2 = s1 & (lead | (rng.random((draws, n)) < pi2))
    T = (s2 * (fail / pi)).sum(axis=1)
    exact_var = float(np.sum(1.0 / pi[fail] - 1.0))
    return float(T.mean()), float(fail.sum()), float(T.var()), exact_var


def main(argv: list[str]) -> None:
    if argv[:1] == ["check"]:
        mean, total, var, exact = check()
        print(f"mean {mean:.3f} vs total {total:.0f}; variance {var:.2f} vs exact {exact:.2f}")
        return
    if argv[:1] != ["run"]:
        sys.exit(__doc__)
    fresh = Path(argv[argv.index("--fresh") + 1]) if "--fresh" in argv else None
    out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else Path("docs/suite")
    doc = run(fresh, out, " ".join(argv))
    print((out / "screen_frontier.md").read_text())
    print(f"{doc['seconds']} s")


if __name__ == "__main__":
    main(sys.argv[1:])
