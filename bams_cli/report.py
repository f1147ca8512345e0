"""The study report: one self-contained HTML file, summary.json and summary.md.

Figures are matplotlib PNGs embedded as data URIs, so the HTML opens anywhere without the
workspace beside it. Every number in the report is in summary.json (documented in the
README), so CI can read what a person sees.
"""

from __future__ import annotations

import base64
import html
import io
import re
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

SUMMARY_KEYS = (
    "schema_version",
    "tool_version",
    "generated_at",
    "workspace",
    "headline",
    "notices",
    "study",
    "simulation_spent",
    "model",
    "batches",
    "estimates",
    "estimate_history",
    "trends",
    "stopping",
    "gp_estimate",
    "confirmed_failures",
    "failures_found",
    "diverse_failures",
    "truth",
    "figures",
)

# An image that fails to decode leaves naturalWidth at 0; the page records the count in
# its title so a headless browser (and the test that drives it) can read it back, and
# whether the headline ends within the first screen.
IMAGE_CHECK = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  var head = document.getElementById('headline');
  var seen = head && head.getBoundingClientRect().bottom <= window.innerHeight;
  document.title = 'images-ok ' + (imgs.length - bad.length) + '/' + imgs.length +
    (seen ? ' headline-in-first-screen' : ' headline-below-first-screen');
});
</script>"""

CSS = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
table { border-collapse: collapse; margin: 0.8em 0; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
img { max-width: 100%; border: 1px solid #eee; }
.note { color: #666; font-size: 0.9em; }
.warn { color: #a40; }
.banner { padding: 0.7em 1em; margin: 0.8em 0; border-radius: 4px; border: 1px solid; }
.banner.warning { background: #fff3e0; border-color: #e65100; color: #6d2a00; font-weight: 600; }
.banner.info { background: #e8f1fb; border-color: #1e63b8; color: #123d70; }
"""


def _png(fig: plt.Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def pool_map(
    XY: NDArray[np.float64],
    p: NDArray[np.float64],
    picks: list[tuple[int, NDArray[np.int64]]],
    *,
    projected: bool,
    gamma: float,
) -> str:
    """The pool coloured by p_n with each batch's picks marked (paper Figure 2c)."""
    fig, ax = plt.subplots(figsize=(7, 6))
    order = np.argsort(p)  # likely failures drawn last, on top
    sc = ax.scatter(
        XY[order, 0], XY[order, 1], c=p[order], s=3, cmap="viridis", vmin=0, vmax=1, rasterized=True
    )
    fig.colorbar(sc, ax=ax, label=f"p_n = P(f <= {gamma:g})")
    markers = ["o", "s", "^", "D", "v", "P", "X", "*"]
    for k, (batch, idx) in enumerate(picks):
        ax.scatter(
            XY[idx, 0],
            XY[idx, 1],
            s=36,
            facecolors="none",
            edgecolors=f"C{(k + 1) % 10}",
            marker=markers[k % len(markers)],
            linewidths=1.2,
            label=f"batch {batch} ({len(idx)})",
        )
    ax.set_xlabel("projection 1 (PCA of the reduced pool)" if projected else "z0")
    ax.set_ylabel("projection 2" if projected else "z1")
    ax.set_title("pool coloured by failure probability, picks marked")
    if picks:
        ax.legend(loc="best", fontsize=8)
    return _png(fig)


def rate_plot(estimates: list[dict[str, Any]], truth_rates: list[float] | None) -> str:
    """The rate estimate with its interval for each gamma (paper Figure 4)."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    x = np.arange(len(estimates))
    p = np.array([e["p_hat"] for e in estimates])
    lo = np.array([e["ci_low"] for e in estimates])
    hi = np.array([e["ci_high"] for e in estimates])
    # Clipped at 0: matplotlib refuses a negative error bar (an interval edited by hand).
    yerr = [np.maximum(p - lo, 0.0), np.maximum(hi - p, 0.0)]
    ax.errorbar(x, p, yerr=yerr, fmt="o", capsize=6, label="IS estimate and interval")
    if truth_rates is not None:
        ax.scatter(
            x, truth_rates, marker="x", color="C3", s=60, zorder=3, label="true rate (ground truth)"
        )
    ax.set_xticks(x, [f"gamma = {e['gamma']:g}" for e in estimates])
    ax.set_ylabel("failure rate")
    ax.set_xlabel("failure threshold")
    ax.set_title(f"failure-rate estimate, {int(round(estimates[0]['confidence'] * 100))}% interval")
    ax.legend(fontsize=8)
    return _png(fig)


def recall_plot(curves: dict[int, NDArray[np.float64]], grid: NDArray[np.float64]) -> str:
    """Retention-recall after each batch (paper Figures 5 and 7)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for batch, recall in sorted(curves.items()):
        ax.plot(grid, recall, label=f"after batch {batch}")
    ax.set_xlabel("retention (units of p N, the number of failures)")
    ax.set_ylabel("recall of true failures")
    ax.set_ylim(0, 1.02)
    ax.set_title("retention-recall: segments sorted by p_n")
    ax.legend(fontsize=8)
    return _png(fig)


def _table(columns: list[str], rows: list[list[Any]], left: set[str] | None = None) -> str:
    left = left or set()
    head = "".join(f'<th class="{"l" if c in left else ""}">{html.escape(c)}</th>' for c in columns)
    body = []
    for row in rows:
        cells = []
        for c, v in zip(columns, row, strict=True):
            text = f"{v:.4g}" if isinstance(v, float) else str(v)
            cells.append(f'<td class="{"l" if c in left else ""}">{html.escape(text)}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'


def _sig(x: float) -> str:
    return f"{x:.2g}" if x >= 1e-3 else f"{x:.1e}"


def headline(
    estimates: list[dict[str, Any]],
    gp_rows: list[dict[str, Any]],
    failures: list[dict[str, Any]],
    spent: dict[str, Any],
    gamma: float,
) -> dict[str, str]:
    """The report's first lines, for the first gamma: the rate with its interval, the
    failures confirmed, the runs spent (``text``), and what sets the interval's width
    (``width``). Without an estimate, the model's own rate, marked as such."""
    per_level = spent["per_level"]
    n0 = per_level.get("0", {}).get("count", 0)
    cheap = sum(v["count"] for k, v in per_level.items() if k != "0")
    confirmed = sum(1 for f in failures if f["status"] == "confirmed" and gamma in f["fails_at"])
    leads = sum(1 for f in failures if f["status"] == "lead")
    runs = f"{n0} level-0" + (f" and {cheap} cheap" if cheap or len(per_level) > 1 else "")
    found = f"{confirmed} failure{'s' if confirmed != 1 else ''} confirmed at level 0" + (
        f" ({leads} more seen only at a cheap level)" if leads else ""
    )
    e = next((r for r in estimates if r["gamma"] == gamma), None)
    if e is not None:
        rate = e["p_hat"]
        one_in = f" (about 1 in {round(1 / rate):,})" if rate > 0 else ""
        text = (
            f"failure rate {_sig(rate)} per segment{one_in}; "
            f"{100 * e['confidence']:g}% interval {_sig(e['ci_low'])} to {_sig(e['ci_high'])}; "
            f"{found}; {runs} runs spent"
        )
        plans = e.get("plans") or [e.get("plan", "?")]
        by = (
            f"plan {plans[0]}"
            if len(plans) == 1
            else f"plans {', '.join(map(str, plans[:-1]))} and {plans[-1]} (the estimate's stages)"
        )
        width = (
            f"The interval rests on {e['failures_sampled']} failure"
            f"{'s' if e['failures_sampled'] != 1 else ''} among {e['n_sampled']} segments "
            f"sampled by {by}"
            + (f", beside {e['failures_known']} known before it" if e.get("failures_known") else "")
            + "; its upper end also allows for one failure the sample may have missed, so "
            "more samples (a larger `estimate --plan --samples K`) narrow it."
        )
        if e.get("variance_note"):
            width += f" {e['variance_note']}"
        return {"text": text, "width": width}
    g = next((r for r in gp_rows if r["gamma"] == gamma), None)
    model = (
        f"the model's own estimate is {_sig(g['gp_p_hat'])} per segment (mean p_n: it leans on "
        "the model, so no interval is claimed)"
        if g is not None
        else "no model fitted yet"
    )
    return {
        "text": f"no failure-rate estimate yet; {found}; {runs} runs spent",
        "width": f"An estimate needs `bams-cli estimate --plan`, its runs and `bams-cli "
        f"estimate`; until then {model}.",
    }


def render_html(summary: dict[str, Any], figures: dict[str, str]) -> str:
    s = summary
    study = s["study"]
    head = s["headline"]
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>bams-cli report</title>",
        f"<style>{CSS}</style>{IMAGE_CHECK}</head><body>",
        "<h1>bams-cli study report</h1>",
        f"<p id='headline' class='headline'><b>{html.escape(head['text'][:1].upper() + head['text'][1:])}.</b></p>",
        f"<p class='note'>{html.escape(head['width'])} Failures found: "
        "<a href='failures.csv'>failures.csv</a>.</p>",
        *_banners(s["notices"]),
        f"<p class='note'>workspace {html.escape(s['workspace'])}, generated {s['generated_at']} "
        f"by bams-cli {s['tool_version']}</p>",
        "<h2>Study</h2>",
        _table(
            ["setting", "value"],
            [
                ["pool size", study["pool_size"]],
                ["reduced dimension", study["dim"]],
                ["gammas", ", ".join(f"{g:g}" for g in study["gammas"])],
                [
                    "levels (cost)",
                    ", ".join(f"{lv['name']} ({lv['cost']:g})" for lv in study["levels"]),
                ],
                ["seed", study["seed"]],
                ["batches", len(s["batches"])],
            ],
            left={"setting", "value"},
        ),
        "<h3>Simulation spent</h3>",
        _table(
            ["level", "simulations", "cost"],
            [[lv, v["count"], v["cost"]] for lv, v in s["simulation_spent"]["per_level"].items()]
            + [["total", s["simulation_spent"]["count"], s["simulation_spent"]["cost"]]],
            left={"level"},
        ),
    ]
    model = s.get("model")
    if model:
        hp = model["hyperparameters"]
        rows = [
            [
                "0 (theta0)",
                model["n_observations_per_level"][0],
                hp["outputscale0"] ** 0.5,
                ", ".join(f"{v:.3g}" for v in hp["lengthscales0"]),
                hp["noise"][0] ** 0.5,
            ]
        ]
        for lv, (sc, ells) in enumerate(
            zip(hp["outputscales"], hp["lengthscales"], strict=True), 1
        ):
            rows.append(
                [
                    f"{lv} (discrepancy)",
                    model["n_observations_per_level"][lv],
                    sc**0.5,
                    ", ".join(f"{v:.3g}" for v in ells),
                    hp["noise"][lv] ** 0.5,
                ]
            )
        parts += [
            "<h3>Model</h3>",
            _table(
                ["level", "observations", "output sd", "lengthscales", "noise sd"],
                rows,
                left={"level", "lengthscales"},
            ),
            f"<p class='note'>constant mean {hp['mean']:.4g}; log marginal likelihood "
            f"{model['log_marginal_likelihood']:.4g}; "
            f"{'model up to date' if model['fresh'] else 'model stale (see the top of the report)'}</p>",
        ]
        parts += [
            f"<p class='warn'>fit warning: {html.escape(w)}</p>" for w in model.get("warnings", [])
        ]
    parts.append("<h2>Batches</h2>")
    if s["batches"]:
        parts.append(
            _table(
                [
                    "batch",
                    "strategy",
                    "picks",
                    "per level",
                    "per cluster",
                    "cost",
                    "mean level-0 f of picks",
                    "SE",
                    "n",
                    "pending",
                    "abandoned",
                ],
                [
                    [
                        b["batch"],
                        b["strategy"],
                        b["picks"],
                        _fmt_counts(b["picks_per_level"]),
                        _fmt_counts(b["picks_per_cluster"]),
                        b["cost"],
                        _maybe(b["mean_f0"]),
                        _maybe(b["mean_f0_se"]),
                        b["n_f0"],
                        b["pending"],
                        b.get("abandoned", 0),
                    ]
                    for b in s["batches"]
                ],
                left={"strategy", "per level", "per cluster"},
            )
        )
        parts.append(
            "<p class='note'>Mean level-0 f over the picks whose level-0 value is known "
            f"({'from the ground truth table' if s['truth'] else 'from the observation log'}); "
            "the paper's Table 1. Blank where no pick's level-0 value is known yet (only "
            "cheap-level picks, or results pending); pending: picks without a result; "
            "abandoned: picks recorded as never coming back (bams-cli abandon).</p>"
        )
    parts.append("<h2>Trends, and when to stop</h2>")
    if s["trends"]:
        parts.append(
            _table(
                [
                    "batch",
                    "cost per level",
                    "confirmed",
                    "confirmed so far",
                    "model's rate",
                    "sd bound",
                    "J before",
                    "J after",
                    "J decrease per cost",
                ],
                [
                    [
                        t["batch"],
                        ", ".join(f"{k}: {v:g}" for k, v in t["cost_per_level"].items()),
                        t["confirmed"],
                        t["confirmed_so_far"],
                        _na(t["gp_rate"], ".3g"),
                        _na(t["gp_sd_bound"], ".2g"),
                        _na(t["j_before"], ".3g"),
                        _na(t["j_after"], ".3g"),
                        _na(t["j_decrease_per_cost"], ".3g"),
                    ]
                    for t in s["trends"]
                ],
            )  # fmt: skip
        )
        parts.append(
            "<p class='note'>Confirmed: level-0 failures at the first gamma that the batch's "
            "requests found. Model's rate: mean p_n of the model fitted on the results up to "
            "that batch, with the Proposition-1 bound on its sd (a model's estimate, not "
            "design-unbiased). J: the pool's mean expected point variance before and after the "
            "batch, as select computed it (blank for batches written before it was stored).</p>"
        )
    if len(s["estimate_history"]) > 1:
        parts.append("<h3>Every estimate made</h3>")
        parts.append(
            _table(
                ["plan", "design", "K", "p_hat", "interval low", "interval high"],
                [
                    [
                        h["plan"],
                        h["design"],
                        h["samples_K"],
                        _na(h["p_hat"], ".3g"),
                        _na(h["ci_low"], ".3g"),
                        _na(h["ci_high"], ".3g"),
                    ]
                    for h in s["estimate_history"]
                ],
            )  # fmt: skip
        )
    parts += [f"<p>{html.escape(line)}</p>" for line in stopping_lines(s["stopping"])]
    if "pool_map" in figures:
        parts += ["<h2>Pool map</h2>", _img(figures["pool_map"], "pool coloured by p_n with picks")]
    parts.append("<h2>Failure-rate estimate</h2>")
    if s["estimates"]:
        parts.append(f"<p class='note'>From estimate plan {s['estimates'][0]['plan']}.</p>")
        parts.append(
            _table(
                [
                    "gamma",
                    "p_hat",
                    "se",
                    "interval",
                    "relative variance",
                    "sampled",
                    "failures found",
                ],
                [
                    [
                        e["gamma"],
                        e["p_hat"],
                        _na(e["se"]),
                        f"[{e['ci_low']:.4g}, {e['ci_high']:.4g}]",
                        _na(e["rel_var"]),
                        e["n_sampled"],
                        e["distinct_failures_found"],
                    ]
                    for e in s["estimates"]
                ],
            )
        )
        parts += [f"<p class='note'>{html.escape(n)}</p>" for n in estimate_notes(s["estimates"])]
        if "rate" in figures:
            parts.append(_img(figures["rate"], "rate estimate with interval"))
    else:
        parts.append(
            "<p>No estimate yet: run <code>bams-cli estimate --plan</code>, simulate, ingest, "
            "then <code>bams-cli estimate</code>.</p>"
        )
    if s["gp_estimate"]:
        parts.append(
            _table(
                ["gamma", "GP mean p_n", "Var bound mean p(1-p)"],
                [[g["gamma"], g["gp_p_hat"], g["gp_var_bound"]] for g in s["gp_estimate"]],
            )
        )
    parts.append("<h2>Confirmed failures</h2>")
    if s["confirmed_failures"]:
        cols = list(s["confirmed_failures"][0].keys())
        parts.append(
            _table(
                cols,
                [[_cell(r[c]) for c in cols] for r in s["confirmed_failures"]],
                left={"segment_id", "fails_at_gamma"},
            )
        )
        parts.append(
            "<p class='note'>Segments simulated at level 0 with f &lt;= gamma for at least "
            "one gamma (batches and estimate plans alike).</p>"
        )
    else:
        parts.append("<p>None yet: no level-0 result is at or below a gamma.</p>")
    parts.append("<h2>Diverse likely failures</h2>")
    if s["diverse_failures"]:
        cols = list(s["diverse_failures"][0].keys())
        parts.append(
            _table(cols, [[r[c] for c in cols] for r in s["diverse_failures"]], left={"segment_id"})
        )
        parts.append(
            "<p class='note'>Chosen by a determinantal point process (greedy MAP) over the "
            "highest-p_n segments whose level-0 value is unknown: likely and unlike each "
            "other. observed_f1 and up: cheap-level results, leads until level 0 confirms "
            "them.</p>"
        )
    elif s["model"] is None:
        parts.append("<p>No model yet: run <code>bams-cli fit</code>.</p>")
    truth = s.get("truth")
    if truth:
        parts.append("<h2>Against ground truth</h2>")
        parts.append(
            _table(
                ["gamma", "true rate", "true failures", "estimate recall"],
                [
                    [g, r, f, _maybe(er)]
                    for g, r, f, er in zip(
                        study["gammas"],
                        truth["rate"],
                        truth["failures"],
                        truth["estimate_recall"],
                        strict=True,
                    )
                ],
            )
        )
        if "recall" in figures:
            parts.append(_img(figures["recall"], "retention-recall per batch"))
    parts.append("</body></html>")
    return "\n".join(parts)


def _banners(notices: list[dict[str, str]]) -> list[str]:
    """The notices as boxes at the top of the page; `commands` in them as code."""
    out = []
    for n in notices:
        text = re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(n["text"]))
        out.append(
            f"<div class='banner {html.escape(n['severity'])}' role='alert' "
            f"data-kind='{html.escape(n['kind'])}'>{text}</div>"
        )
    return out


def _cell(v: Any) -> Any:
    return ", ".join(f"{x:g}" for x in v) if isinstance(v, list) else v


def _na(v: float | None, spec: str | None = None) -> Any:
    """An estimate's number, or "n/a" where it is undefined (null; its note says why)."""
    if v is None:
        return "n/a"
    return v if spec is None else format(v, spec)


def estimate_notes(estimates: list[dict[str, Any]]) -> list[str]:
    """One line per note of the estimate rows: what se rests on, why rel_var is undefined."""
    out = []
    for e in estimates:
        for key, what in (("variance_note", "se"), ("rel_var_note", "relative variance")):
            if e.get(key):
                out.append(f"gamma {e['gamma']:g}, {what}: {e[key]}")
    return out


def _maybe(v: Any) -> Any:
    return "" if v is None else v


def _fmt_counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in d.items())


def render_markdown(summary: dict[str, Any]) -> str:
    s = summary
    head = s["headline"]
    lines = [
        f"## bams-cli report ({s['workspace']})",
        "",
        f"**{head['text'][:1].upper() + head['text'][1:]}.** {head['width']}",
        "",
    ]
    for n in s["notices"]:
        # GitHub renders these as alert boxes; elsewhere they read as quoted lines.
        lines += [
            f"> [!{'WARNING' if n['severity'] == 'warning' else 'NOTE'}]",
            f"> {n['text']}",
            "",
        ]
    spent = s["simulation_spent"]
    lines.append(
        f"Pool of {s['study']['pool_size']} segments; {len(s['batches'])} batches; "
        f"{spent['count']} simulations costing {spent['cost']:g} level-0 runs."
    )
    lines.append("")
    if s["estimates"]:
        lines += [
            "| gamma | p_hat | se | interval | rel. variance | failures found |",
            "|---|---|---|---|---|---|",
        ]
        for e in s["estimates"]:
            lines.append(
                f"| {e['gamma']:g} | {e['p_hat']:.4g} | {_na(e['se'], '.3g')} | [{e['ci_low']:.4g}, {e['ci_high']:.4g}] "
                f"| {_na(e['rel_var'], '.3g')} | {e['distinct_failures_found']} |"
            )
        lines.append("")
        lines += [f"{n}\n" for n in estimate_notes(s["estimates"])]
    if s["batches"]:
        lines += [
            "| batch | strategy | picks | cost | mean level-0 f (SE) | pending | abandoned |",
            "|---|---|---|---|---|---|---|",
        ]
        for b in s["batches"]:
            mf = (
                ""
                if b["mean_f0"] is None
                else f"{b['mean_f0']:.3g} ({_maybe(b['mean_f0_se']) if b['mean_f0_se'] is None else format(b['mean_f0_se'], '.2g')})"
            )
            lines.append(
                f"| {b['batch']} | {b['strategy']} | {b['picks']} | {b['cost']:g} | {mf} "
                f"| {b['pending']} | {b.get('abandoned', 0)} |"
            )
        lines.append("")
    lines += trend_lines(s)
    confirmed = s["confirmed_failures"]
    lines.append(
        f"Confirmed failures (level 0, f <= a gamma): {len(confirmed)}"
        + (": " + ", ".join(str(r["segment_id"]) for r in confirmed[:10]) if confirmed else "")
        + (", ..." if len(confirmed) > 10 else "")
        + "."
    )
    if s["diverse_failures"]:
        lines.append(
            "Likely failures (level-0 value unknown, by p_n): "
            + ", ".join(f"{r['segment_id']} (p_n {r['p_n']:.2g})" for r in s["diverse_failures"])
            + "."
        )
    lines.append("")
    if s.get("truth"):
        t = s["truth"]
        lines.append(
            "True rate "
            + ", ".join(f"{r:.4g}" for r in t["rate"])
            + "; estimate recall "
            + ", ".join("" if r is None else f"{r:.3f}" for r in t["estimate_recall"])
            + "."
        )
    return "\n".join(lines) + "\n"


def trend_lines(summary: dict[str, Any]) -> list[str]:
    """The trend across batches and the stopping signal, as Markdown (summary.md)."""
    lines: list[str] = []
    trends = summary["trends"]
    if trends:
        lines += [
            "| batch | cost per level | confirmed (so far) | model's rate (sd bound) | J before -> after | J decrease per cost |",
            "|---|---|---|---|---|---|",
        ]
        for t in trends:
            rate = "" if t["gp_rate"] is None else f"{t['gp_rate']:.3g} ({t['gp_sd_bound']:.2g})"
            j = "" if t["j_before"] is None else f"{t['j_before']:.3g} -> {t['j_after']:.3g}"
            dj = "" if t["j_decrease_per_cost"] is None else f"{t['j_decrease_per_cost']:.3g}"
            cost = ", ".join(f"{k}: {v:g}" for k, v in t["cost_per_level"].items())
            lines.append(
                f"| {t['batch']} | {cost} | {t['confirmed']} ({t['confirmed_so_far']}) | {rate} | {j} | {dj} |"
            )
        lines.append("")
    history = summary["estimate_history"]
    if len(history) > 1:
        lines += ["| plan | design | K | p_hat | interval |", "|---|---|---|---|---|"]
        for h in history:
            lines.append(
                f"| {h['plan']} | {h['design']} | {h['samples_K']:g} | {h['p_hat']:.3g} "
                f"| [{h['ci_low']:.3g}, {h['ci_high']:.3g}] |"
            )
        lines.append("")
    lines += [f"{line}\n" for line in stopping_lines(summary["stopping"])]
    return lines


def stopping_lines(stop: dict[str, Any]) -> list[str]:
    """When to stop, in sentences (summary.md and the page)."""
    out = []
    if stop["j_decrease_per_cost_last_batches"]:
        out.append(
            "J decrease per unit cost, last batches: "
            + ", ".join(f"{v:.3g}" for v in stop["j_decrease_per_cost_last_batches"])
            + " (as it nears 0, discovery has little uncertainty left to remove)."
        )
    if stop["expected_failures_next_batch"] is not None:
        out.append(
            f"Expected level-0 failures if the next batch ran {stop['next_batch_level0_runs']} "
            "level-0 runs at the likeliest unconfirmed segments: "
            f"{stop['expected_failures_next_batch']:.2g} (by the model's p_n)."
        )
    if stop["samples_for_width_equal_to_rate"] is not None:
        out.append(
            "An interval as wide as the rate itself would need about "
            f"{stop['samples_for_width_equal_to_rate']:,.0f} samples (`estimate --plan --samples K`;"
            " the width shrinks as 1/sqrt(K))."
        )
    return out
