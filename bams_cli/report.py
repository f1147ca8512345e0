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
    "spend",
    "predicted_vs_found",
    "p_distribution",
    "groups",
    "diverse_failures",
    "truth",
    "figures",
)

#: The page lists the first this many failures found; failures.csv holds them all.
FAILURES_SHOWN = 50

# An image that fails to decode leaves naturalWidth at 0; the page records the count in
# its title so a headless browser (and the test that drives it) can read it back, whether
# the headline ends within the first screen, and whether the page is wider than the
# window (a table or plot that pushes it sideways).
IMAGE_CHECK = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  var head = document.getElementById('headline');
  var seen = head && head.getBoundingClientRect().bottom <= window.innerHeight;
  var wide = document.documentElement.scrollWidth > window.innerWidth ||
    document.body.scrollWidth > window.innerWidth;
  document.title = 'images-ok ' + (imgs.length - bad.length) + '/' + imgs.length +
    (seen ? ' headline-in-first-screen' : ' headline-below-first-screen') +
    (wide ? ' overflows-sideways' : ' fits-width') +
    ' viewport-' + window.innerWidth + 'x' + window.innerHeight;
});
</script>"""

CSS = """
*, *::before, *::after { box-sizing: border-box; }
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 1.2em auto;
  padding: 0 1em; color: #222; line-height: 1.4; overflow-wrap: anywhere; }
h1 { margin: 0 0 0.3em; font-size: 1.5em; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 1.6em; }
.headline { font-size: 1.15em; margin: 0.3em 0; }
.scroll { overflow-x: auto; max-width: 100%; }
table { border-collapse: collapse; margin: 0.8em 0; overflow-wrap: normal; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
img { max-width: 100%; height: auto; border: 1px solid #eee; display: block; margin: 0.6em 0; }
.note { color: #555; font-size: 0.9em; }
.warn { color: #a40; }
.banner { padding: 0.7em 1em; margin: 0.8em 0; border-radius: 4px; border: 1px solid; }
.banner.warning { background: #fff3e0; border-color: #e65100; color: #6d2a00; font-weight: 600; }
.banner.info { background: #e8f1fb; border-color: #1e63b8; color: #123d70; }
section.truth { border: 2px dashed #7b1fa2; padding: 0 1em 1em; margin-top: 2em; background: #faf5fc; }
section.truth h2 { color: #6a1b9a; }
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
    ax.set_title(
        "2-D projection of the pool: p_n and picks (failures may hide under other points)"
        if projected
        else "the pool coloured by failure probability, picks marked",
        fontsize=10,
    )
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
    ax.set_ylabel("failure rate per segment")
    ax.set_ylim(bottom=0)
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


def rate_band_plot(trends: list[dict[str, Any]], history: list[dict[str, Any]]) -> str:
    """The model's rate after each batch with its band, and every estimate made with its
    interval, on one axis from 0 (the report's trend)."""
    fig, ax = plt.subplots(figsize=(7, 3.6))
    rows = [t for t in trends if t["gp_rate"] is not None]
    top = 0.0
    if rows:
        x = np.array([t["batch"] for t in rows], float)
        m = np.array([t["gp_rate"] for t in rows])
        sd = np.array([t["gp_sd_bound"] for t in rows])
        lo, hi = np.maximum(m - 2 * sd, 0.0), m + 2 * sd
        if len(rows) > 1:
            ax.fill_between(x, lo, hi, color="C0", alpha=0.18, linewidth=0)
        ax.errorbar(
            x, m, yerr=[m - lo, hi - m], fmt="o-", color="C0", capsize=4, alpha=0.9,
            label="model's rate after the batch (mean p_n), ± 2 sd bound",
        )  # fmt: skip
        top = max(top, 3 * float(m.max()))
    seen: dict[int, int] = {}
    for j, h in enumerate(history):
        if h["p_hat"] is None:
            continue
        k = seen[h["after_batch"]] = seen.get(h["after_batch"], -1) + 1
        x0 = h["after_batch"] + 0.2 + 0.12 * k
        p, lo, hi = h["p_hat"], h["ci_low"], h["ci_high"]
        conf = f"{100 * (h.get('confidence') or 0):g}%"
        ax.errorbar(
            [x0], [p], yerr=[[max(p - lo, 0.0)], [max(hi - p, 0.0)]], fmt="s", color="C3",
            capsize=6, label=f"estimate with its {conf} interval" if j == 0 else None,
        )  # fmt: skip
        ax.annotate(f"plan {h['plan']}", (x0, hi), textcoords="offset points", xytext=(4, 2),
                    fontsize=8, color="C3")  # fmt: skip
        top = max(top, 1.15 * hi)
    ax.set_ylim(0, top if top > 0 else None)
    batches = [t["batch"] for t in trends]
    if batches:
        ax.set_xticks(batches)
    ax.set_xlabel("batch (an estimate sits right of the last batch before its plan)")
    ax.set_ylabel("failure rate per segment")
    ax.set_title("the failure rate across the study", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    return _png(fig)


def predicted_plot(trends: list[dict[str, Any]]) -> str:
    """Failures found against the count the model predicted before the results: over the
    batches with a model before them, cumulative level-0 failures confirmed and the
    cumulative sum of p_n at their level-0 results, ± 2 sd."""
    rows = [t for t in trends if t["predicted_failures"] is not None]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    x = np.array([t["batch"] for t in rows])
    pred = np.cumsum([t["predicted_failures"] for t in rows])
    sd = np.sqrt(np.cumsum([t["predicted_sd"] ** 2 for t in rows]))
    found = np.cumsum([t["confirmed"] for t in rows])
    lo = np.maximum(pred - 2 * sd, 0)
    if len(rows) > 1:
        ax.fill_between(x, lo, pred + 2 * sd, color="C0", alpha=0.18, linewidth=0)
    ax.errorbar(x, pred, yerr=[pred - lo, 2 * sd], fmt="o--", color="C0", capsize=4,
                label="expected by the model before the results (± 2 sd)")  # fmt: skip
    ax.plot(x, found, "s-", color="C3", label="confirmed at level 0")
    ax.set_xticks(x)
    ax.set_ylim(bottom=0, top=max(1.0, float((pred + 2 * sd).max()), float(found.max())) * 1.15)
    ax.set_xlabel("batch")
    ax.set_ylabel("level-0 failures, cumulative")
    ax.set_title("failures found against the model's prediction", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    return _png(fig)


def p_distribution_plot(d: dict[str, Any]) -> str:
    """The model's p_n over the pool on a log scale, the failures it expects in each bin,
    and where the level-0 runs went (at the p_n a model gave before their results)."""
    edges = np.array(d["edges"], float)
    edges[0] = edges[1] / 10**0.5  # the [0, 1e-6) bin drawn half a decade wide
    fig, (top, low) = plt.subplots(
        2, 1, figsize=(7, 4.8), sharex=True, gridspec_kw={"height_ratios": [3, 2]}
    )
    top.stairs(d["unknown"], edges, fill=True, color="C0", alpha=0.35,
               label="segments not yet run at level 0")  # fmt: skip
    top.stairs(d["expected_failures"], edges, color="C3", linewidth=1.8,
               label="failures the model expects there (sum of p_n)")  # fmt: skip
    top.set_yscale("log", nonpositive="clip")
    top.set_ylim(bottom=1e-2)
    top.set_ylabel("segments / failures")
    top.legend(fontsize=8, loc="upper left")
    top.set_title(f"the model's failure probability p_n = P(f <= {d['gamma']:g}) over the pool",
                  fontsize=10)  # fmt: skip
    low.stairs(d["runs"], edges, fill=True, color="C2", alpha=0.45,
               label="level-0 runs, at the p_n before their result")  # fmt: skip
    low.stairs(d["runs_failed"], edges, fill=True, color="C3", alpha=0.9,
               label="failures among them")  # fmt: skip
    low.set_ylabel("level-0 runs")
    low.set_xscale("log")
    low.set_xlabel("p_n (log scale; the leftmost bin holds every p_n below 1e-6)")
    low.legend(fontsize=8, loc="upper left")
    return _png(fig)


def groups_plot(g: dict[str, Any]) -> str:
    """Per cluster or tag: the failures the model expects, those confirmed and the leads;
    beside it the runs spent per level."""
    rows = g["rows"]
    names = [r["group"] for r in rows]
    x = np.arange(len(rows))
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    width = 0.27
    if rows[0]["expected_failures"] is not None:
        left.bar(x - width, [r["expected_failures"] for r in rows], width, color="C0",
                 label="expected (sum of p_n)")  # fmt: skip
    left.bar(x, [r["confirmed"] for r in rows], width, color="C3", label="confirmed")
    left.bar(x + width, [r["leads"] for r in rows], width, color="C1", label="leads")
    left.set_ylabel("failures")
    left.set_title("failures per group", fontsize=10)
    left.legend(fontsize=8)
    bottom = np.zeros(len(rows))
    levels = sorted(rows[0]["runs_per_level"], key=int)
    for lv in levels:
        runs = np.array([r["runs_per_level"][lv] for r in rows], float)
        right.bar(x, runs, 0.6, bottom=bottom, color=f"C{int(lv) + 2}", label=f"level {lv}")
        bottom += runs
    right.set_ylabel("runs")
    right.set_title("runs spent per group", fontsize=10)
    right.legend(fontsize=8)
    for ax in (left, right):
        ax.set_xticks(
            x,
            names,
            rotation=30 if len(rows) > 4 else 0,
            ha="right" if len(rows) > 4 else "center",
            fontsize=8,
        )
        ax.set_xlabel(g["by"])
    fig.tight_layout()
    return _png(fig)


def _table(columns: list[str], rows: list[list[Any]], left: set[str] | None = None) -> str:
    left = left or set()
    head = "".join(f'<th class="{"l" if c in left else ""}">{html.escape(c)}</th>' for c in columns)
    body = []
    for row in rows:
        cells = []
        for c, v in zip(columns, row, strict=True):
            text = f"{v:.4g}" if isinstance(v, float) else "" if v is None else str(v)
            cells.append(f'<td class="{"l" if c in left else ""}">{html.escape(text)}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'


def _sig(x: float) -> str:
    """``x`` to three significant digits (0.0105, 9.02e-04): with two, an interval
    [0.01049, 0.0143] read "0.01 to 0.014", its lower end a twentieth off."""
    if x == 0:
        return "0"
    return f"{x:.3g}" if x >= 1e-3 else f"{x:.2e}"


#: What each interval kind (``estimate --interval``) allows for, as the headline says it.
INTERVAL_KINDS = {
    "gamma": "it is a gamma interval: its upper end also allows for one failure, of the weight "
    "the checked model predicts, that the sample may have missed. ",
    "fay-feuer": "it is Fay and Feuer's interval: its upper end allows for one missed failure "
    "of the largest weight any segment could carry, so it keeps its coverage however wrong "
    "the model (wider than the gamma interval). ",
}


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
    found = (
        f"{confirmed} failure{'s' if confirmed != 1 else ''} confirmed at level 0 (gamma {gamma:g})"
    ) + (f" ({leads} more seen only at a cheap level)" if leads else "")
    e = next((r for r in estimates if r["gamma"] == gamma), None)
    if e is not None:
        rate = e["p_hat"]
        conf = f"{100 * e['confidence']:g}%"
        interval = f"{conf} interval {_sig(e['ci_low'])} to {_sig(e['ci_high'])}"
        abandoned = int(e.get("abandoned") or 0)
        if e.get("p_hat_low") is not None and e.get("p_hat_high") is not None:
            # --failed-as bounds: a range over the abandoned segments, not one rate.
            rate_text = (
                f"failure rate between {_sig(e['p_hat_low'])} and {_sig(e['p_hat_high'])} per "
                f"segment (the {abandoned} abandoned segment{'s' if abandoned != 1 else ''} "
                f"all passing, then all failing); {interval}"
            )
        elif rate == 0 and not e.get("failures_sampled") and not e.get("failures_known"):
            rate_text = (
                f"failure rate at most {_sig(e['ci_high'])} per segment (no failure in the "
                f"estimate's sample; {interval})"
            )
        else:
            one_in = f" (about 1 in {round(1 / rate):,})" if rate > 0 else ""
            rate_text = f"failure rate {_sig(rate)} per segment{one_in}; {interval}"
        done, planned = int(e.get("stages_done") or 1), int(e.get("stages") or 1)
        stage_text = (
            f"; stage {done} of {planned} only: the next `estimate --plan` draws "
            + ("the rest" if done + 1 == planned else f"stage {done + 1}")
            if done < planned
            else ""
        )
        text = f"{rate_text}{stage_text}; {found}; {runs} runs spent"
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
            + (f" ({abandoned} of them abandoned)" if abandoned else "")
            + (
                f", beside {e['failures_known']} known from other level-0 runs"
                if e.get("failures_known")
                else ""
            )
            + "; "
            + INTERVAL_KINDS.get(e.get("interval", "gamma"), "")
            + "More samples (a larger `estimate --plan --samples K`) narrow it."
        )
        if e.get("variance_note"):
            note = str(e["variance_note"])
            width += f" {note[:1].upper()}{note[1:]}"
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
    """The page, top to bottom: the headline, the failures found, the trend across the
    study and when to stop, where the failures are (plots that read in any dimension), the
    estimate's details, the likely failures, the study's settings and model, the 2-D pool
    map, and, only with --truth, the comparison with ground truth, marked as such."""
    s = summary
    head = s["headline"]
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>bams-cli report</title><style>{CSS}</style>{IMAGE_CHECK}</head><body>",
        "<h1>bams-cli study report</h1>",
        f"<p id='headline' class='headline'><b>{html.escape(_cap(head['text']))}.</b></p>",
        f"<p class='note'>{_code(head['width'])} Every failure found: "
        "<a href='failures.csv'>failures.csv</a>.</p>",
        *_banners(s["notices"]),
        f"<p class='note'>workspace {html.escape(s['workspace'])}, generated {s['generated_at']} "
        f"by bams-cli {s['tool_version']}</p>",
    ]
    parts += _failures_section(s)
    parts += _trends_section(s, figures)
    parts += _where_section(s, figures)
    parts += _estimate_section(s, figures)
    parts += _likely_section(s)
    parts += _study_section(s)
    if "pool_map" in figures:
        parts += [
            "<h2>Pool map (a 2-D projection)</h2>",
            "<p class='note'>The pool projected to two dimensions"
            + (f" (PCA of its {s['study']['dim']} reduced coordinates)" if s["study"]["dim"] > 2
               else "")
            + ", coloured by p_n, with each batch's picks marked. Segments far apart in the "
            "pool can land on top of each other here: read the plots above for where the "
            "failures are.</p>",
            _img(figures["pool_map"], "pool coloured by p_n with picks (2-D projection)"),
        ]  # fmt: skip
    parts += _truth_section(s, figures)
    parts.append("</body></html>")
    return "\n".join(parts)


def _cap(text: str) -> str:
    return text[:1].upper() + text[1:]


def _code(text: str) -> str:
    """Escaped text with `commands` set as code."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(text))


def _scroll(table: str) -> str:
    """A table that scrolls on its own when wider than the page, never the page."""
    return f"<div class='scroll'>{table}</div>"


def _failures_section(s: dict[str, Any]) -> list[str]:
    found = s["failures_found"]
    parts = ["<h2>Failures found</h2>"]
    if not found["count"]:
        return parts + [
            "<p>None yet: no level-0 result is at or below a gamma, and no cheap-level result "
            "is at or below the first.</p>"
        ]
    cols = found["columns"]
    rows = [[_cell(r[c]) for c in cols] for r in found["shown"]]
    parts.append(
        f"<p>{found['count']} failure{'s' if found['count'] != 1 else ''} found: "
        f"{found['confirmed']} confirmed at level 0, {found['leads']} lead"
        f"{'s' if found['leads'] != 1 else ''} (failed at a cheap level, level 0 not yet run).</p>"
    )
    parts.append(_scroll(_table(cols, rows, left={"segment_id", "status", "found_by", "fails_at"})))
    more = found["count"] - len(found["shown"])
    if more > 0:
        parts.append(
            f"<p><b>{more} more</b> in <a href='failures.csv'>failures.csv</a> (the first "
            f"{len(found['shown'])} are shown: confirmed first, then by value).</p>"
        )
    parts.append(
        "<p class='note'>status: confirmed (its level-0 value is at or below a gamma) or lead "
        "(a cheap level failed at the first gamma; level 0 has not run). found_by: the batch "
        "or estimate plan whose request returned the failing result. fails_at: the gammas "
        "it fails at. value_L: the metric at level L. Then the pool's pass-through "
        "columns.</p>"
    )
    return parts


def _trends_section(s: dict[str, Any], figures: dict[str, str]) -> list[str]:
    parts = ["<h2>Trends, and when to stop</h2>"]
    if "rate_band" in figures:
        parts.append(_img(figures["rate_band"], "failure rate across batches, with estimates"))
        parts.append(
            "<p class='note'>Blue: the model's rate (mean p_n) after each batch, its band 2 "
            "Proposition-1 sd bounds either side (a loose bound: the band may run off the "
            "top). The band is the model's own uncertainty, which nothing outside the model "
            "checks: it can lie wholly below the true rate, as it does when the model has seen "
            "no failure at level 0. Red: every estimate made, with its interval; unlike the "
            "model's rate it is unbiased whatever the model.</p>"
        )
    if "predicted" in figures:
        parts.append(_img(figures["predicted"], "failures found against the predicted count"))
    pv = s["predicted_vs_found"]
    if pv is not None:
        parts.append(f"<p>{html.escape(predicted_line(pv))}</p>")
    if s["trends"] or s["spend"]["plans"]:
        parts.append(_scroll(_trends_table(s)))
        parts.append(
            "<p class='note'>Runs per level: results in, counted from the observation log. "
            "Failures: level-0 failures at the first gamma among the step's results (so far: "
            "those of every batch up to it). Expected: the failures the model fitted before "
            "the batch's results predicted among its level-0 results (sum of p_n, ± 1 sd). "
            "Model's rate: mean p_n of the model fitted on the results up to that batch, "
            "with the Proposition-1 bound on its sd. J: the pool's mean expected point "
            "variance before and after the batch, as select computed it (blank for batches "
            "written before it was stored).</p>"
        )
        parts.append(_scroll(_spend_table(s)))
    if len(s["estimate_history"]) > 1:
        parts.append("<h3>Every estimate made</h3>")
        parts.append(
            _scroll(
                _table(
                    ["plan", "sample of plans", "after batch", "design", "interval", "K",
                     "p_hat", "interval low", "interval high"],
                    [
                        [h["plan"], ", ".join(map(str, h.get("plans") or [h["plan"]])),
                         h.get("after_batch", ""), h["design"], h.get("interval", "gamma"),
                         h["samples_K"], _na(h["p_hat"], ".3g"), _na(h["ci_low"], ".3g"),
                         _na(h["ci_high"], ".3g")]
                        for h in s["estimate_history"]
                    ],
                )
            )
        )  # fmt: skip
    parts += [f"<p>{_code(line)}</p>" for line in stopping_lines(s["stopping"])]
    return parts


def _trends_table(s: dict[str, Any]) -> str:
    """Batches and estimate plans in the order they were made, each with its spend."""
    levels = sorted(s["simulation_spent"]["per_level"], key=int)
    history = {h["plan"]: h for h in s["estimate_history"]}
    plans = s["spend"]["plans"]
    rows: list[list[Any]] = []

    def blank(v: float | None, spec: str) -> str:
        return "" if v is None else format(v, spec)

    def plan_rows(after: int) -> None:
        for p in plans:
            if p["after_batch"] != after:
                continue
            h = history.get(p["plan"])
            rate = (
                ""
                if h is None or h["p_hat"] is None
                else f"estimate {h['p_hat']:.3g} [{h['ci_low']:.3g}, {h['ci_high']:.3g}]"
            )
            counts = [p["per_level"][lv]["count"] for lv in levels]
            rows.append([f"estimate plan {p['plan']}", *counts, p["cost"], p["confirmed"], "",
                         rate, "", ""])  # fmt: skip

    plan_rows(0)
    for t in s["trends"]:
        expected = (
            ""
            if t["predicted_failures"] is None
            else f"{t['predicted_failures']:.2g} ± {t['predicted_sd']:.2g}"
        )
        rate = "" if t["gp_rate"] is None else f"model {t['gp_rate']:.3g} ({t['gp_sd_bound']:.2g})"
        j = "" if t["j_before"] is None else f"{t['j_before']:.3g} → {t['j_after']:.3g}"
        runs = t.get("runs_per_level", {})
        rows.append([f"batch {t['batch']}", *[runs.get(lv, 0) for lv in levels],
                     _batch_spent(t, s), f"{t['confirmed']} ({t['confirmed_so_far']})",
                     expected, rate, j, blank(t["j_decrease_per_cost"], ".3g")])  # fmt: skip
        plan_rows(t["batch"])
    cols = ["step", *[f"level {lv} runs" for lv in levels], "cost",
            "level-0 failures (so far)", "expected before results",
            "rate: model's (sd bound), or estimate [interval]", "J before → after",
            "J decrease per cost"]  # fmt: skip
    return _table(cols, rows, left={"step"})


def _batch_spent(t: dict[str, Any], s: dict[str, Any]) -> float:
    costs = {str(i): lv["cost"] for i, lv in enumerate(s["study"]["levels"])}
    return float(sum(costs[lv] * c for lv, c in t.get("runs_per_level", {}).items()))


def _spend_table(s: dict[str, Any]) -> str:
    sp = s["spend"]
    levels = sorted(s["simulation_spent"]["per_level"], key=int)
    rows = []
    for key, name in (("discovery", "discovery (batches)"), ("estimate", "estimate plans"),
                      ("other", "results not asked for")):  # fmt: skip
        part = sp[key]
        if key == "other" and not part["count"]:
            continue
        rows.append([name, *[part["per_level"][lv]["count"] for lv in levels], part["count"],
                     part["cost"]])  # fmt: skip
    total = s["simulation_spent"]
    rows.append(["total", *[total["per_level"][lv]["count"] for lv in levels], total["count"],
                 total["cost"]])  # fmt: skip
    return _table(
        ["spend, by purpose", *[f"level {lv} runs" for lv in levels], "runs", "cost"],
        rows,
        left={"spend, by purpose"},
    )


def _where_section(s: dict[str, Any], figures: dict[str, str]) -> list[str]:
    parts = ["<h2>Where the failures are</h2>"]
    if "p_distribution" in figures:
        d = s["p_distribution"]
        parts.append(_img(figures["p_distribution"], "distribution of p_n over the pool"))
        unknown = sum(d["expected_failures"])
        parts.append(
            f"<p class='note'>Top: how many segments not yet run at level 0 the model gives each "
            f"p_n, and the failures it expects among them ({unknown:.3g} in all). Bottom: "
            f"the level-0 runs of batches and plans at the p_n the model gave them before "
            f"their result ({sum(d['runs'])} runs; {d['runs_without_prior']} more had no "
            "model before them), and the failures among them. Failures found at low p_n are "
            "failures the model did not see coming.</p>"
        )
    g = s["groups"]
    if g is not None and g["rows"]:
        levels = sorted(g["rows"][0]["runs_per_level"], key=int)
        parts.append(f"<h3>By {html.escape(g['by'])}</h3>")
        parts.append(
            _scroll(
                _table(
                    [g["by"], "segments", "expected failures (sum p_n)",
                     "expected among not run at level 0", *[f"level {lv} runs" for lv in levels],
                     "confirmed", "leads"],
                    [[r["group"], r["size"], _na(r["expected_failures"], ".3g"),
                      _na(r["expected_unconfirmed"], ".3g"),
                      *[r["runs_per_level"][lv] for lv in levels], r["confirmed"], r["leads"]]
                     for r in g["rows"]],
                    left={g["by"]},
                )
            )
        )  # fmt: skip
        if "groups" in figures:
            parts.append(_img(figures["groups"], f"failures and runs per {g['by']}"))
        parts.append(
            "<p class='note'>"
            + (f"<strong>{html.escape(g['caveat'])}.</strong> " if g.get("caveat") else "")
            + _code(
                f"Groups: {g['how']}. Confirmed: level-0 failures at the first gamma; leads: "
                "cheap-level failures not yet run at level 0. A group whose expected failures "
                "far exceed those confirmed, with few runs, is where the next runs could look "
                "(`bams-cli report --by COLUMN` groups by a pass-through column instead)."
            )
            + "</p>"
        )
    if len(parts) == 1:
        parts.append("<p>No model yet: run <code>bams-cli fit</code>.</p>")
    return parts


def _estimate_section(s: dict[str, Any], figures: dict[str, str]) -> list[str]:
    parts = ["<h2>Failure-rate estimate</h2>"]
    if s["estimates"]:
        e0 = s["estimates"][0]
        kind = e0.get("interval", "gamma")
        parts.append(
            f"<p class='note'>From estimate plan {e0['plan']}; "
            f"{100 * e0['confidence']:g}% {'Fay-Feuer' if kind == 'fay-feuer' else 'gamma'} "
            "intervals.</p>"
        )
        parts.append(
            _scroll(
                _table(
                    ["gamma", "p_hat", "se", "interval", "relative variance", "sampled",
                     "failures found"],
                    [[e["gamma"], e["p_hat"], _na(e["se"]),
                      f"[{e['ci_low']:.4g}, {e['ci_high']:.4g}]", _na(e["rel_var"]),
                      e["n_sampled"], e["distinct_failures_found"]]
                     for e in s["estimates"]],
                )
            )
        )  # fmt: skip
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
            _scroll(
                _table(
                    ["gamma", "GP mean p_n", "Var bound mean p(1-p)"],
                    [[g["gamma"], g["gp_p_hat"], g["gp_var_bound"]] for g in s["gp_estimate"]],
                )
            )
        )
    return parts


def _likely_section(s: dict[str, Any]) -> list[str]:
    parts = ["<h2>Diverse likely failures</h2>"]
    if s["diverse_failures"]:
        cols = list(s["diverse_failures"][0].keys())
        parts.append(
            _scroll(
                _table(
                    cols, [[r[c] for c in cols] for r in s["diverse_failures"]], left={"segment_id"}
                )
            )
        )
        parts.append(
            "<p class='note'>Predictions, not findings: chosen by a determinantal point "
            "process (greedy MAP) over the highest-p_n segments whose level-0 value is "
            "unknown, likely and unlike each other. observed_f1 and up: cheap-level results, "
            "leads until level 0 confirms them.</p>"
        )
    elif s["model"] is None:
        parts.append("<p>No model yet: run <code>bams-cli fit</code>.</p>")
    return parts


def _study_section(s: dict[str, Any]) -> list[str]:
    study = s["study"]
    parts = [
        "<h2>Study</h2>",
        _scroll(
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
            )
        ),
        "<h3>Simulation spent</h3>",
        _scroll(
            _table(
                ["level", "simulations", "cost"],
                [
                    [lv, v["count"], v["cost"]]
                    for lv, v in s["simulation_spent"]["per_level"].items()
                ]
                + [["total", s["simulation_spent"]["count"], s["simulation_spent"]["cost"]]],
                left={"level"},
            )
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
        scales = hp.get("scales") or [1.0] * len(hp["outputscales"])
        for lv, (sc, ells) in enumerate(
            zip(hp["outputscales"], hp["lengthscales"], strict=True), 1
        ):
            rho = float(scales[lv - 1])
            rows.append(
                [
                    f"{lv} (discrepancy{'' if rho == 1.0 else f'; {rho:.3g} x level 0'})",
                    model["n_observations_per_level"][lv],
                    sc**0.5,
                    ", ".join(f"{v:.3g}" for v in ells),
                    hp["noise"][lv] ** 0.5,
                ]
            )
        parts += [
            "<h3>Model</h3>",
            _scroll(
                _table(
                    ["level", "observations", "output sd", "lengthscales", "noise sd"],
                    rows,
                    left={"level", "lengthscales"},
                )
            ),
            f"<p class='note'>constant mean {hp['mean']:.4g}; log marginal likelihood "
            f"{model['log_marginal_likelihood']:.4g}; "
            f"{'model up to date' if model['fresh'] else 'model stale (see the top of the report)'}</p>",
        ]
        parts += [
            f"<p class='warn'>fit warning: {html.escape(w)}</p>" for w in model.get("warnings", [])
        ]
    parts.append("<h3>Batches</h3>")
    if s["batches"]:
        truth = bool(s["truth"])
        parts.append(
            _scroll(
                _table(
                    ["batch", "strategy", "picks", "per level", "per cluster", "cost",
                     "mean level-0 f of picks" + (" (ground truth)" if truth else ""), "SE", "n",
                     "pending", "abandoned"],
                    [[b["batch"], b["strategy"], b["picks"], _fmt_counts(b["picks_per_level"]),
                      _fmt_counts(b["picks_per_cluster"]), b["cost"], _maybe(b["mean_f0"]),
                      _maybe(b["mean_f0_se"]), b["n_f0"], b["pending"], b.get("abandoned", 0)]
                     for b in s["batches"]],
                    left={"strategy", "per level", "per cluster"},
                )
            )
        )  # fmt: skip
        parts.append(
            "<p class='note'>Mean level-0 f over the picks whose level-0 value is known "
            f"({'from the ground truth table (--truth)' if truth else 'from the observation log'}); "
            "the paper's Table 1. Blank where no pick's level-0 value is known yet (only "
            "cheap-level picks, or results pending); pending: picks without a result; "
            "abandoned: picks recorded as never coming back (bams-cli abandon).</p>"
        )
    else:
        parts.append(
            "<p>None yet: <code>bams-cli select --strategy random --mixed-fidelity</code> "
            "makes the first.</p>"
        )
    return parts


def _truth_section(s: dict[str, Any], figures: dict[str, str]) -> list[str]:
    truth = s.get("truth")
    if not truth:
        return []
    parts = [
        "<section class='truth' id='ground-truth' data-truth='1'>",
        "<h2>Against ground truth (--truth)</h2>",
        "<p><b>Only because --truth was given</b> (sample data, or a study re-run on a "
        "simulated pool): a real study has no ground truth, and nothing above uses it, "
        "except the batches' mean level-0 f, marked there.</p>",
        _scroll(
            _table(
                ["gamma", "true rate", "true failures", "estimate recall"],
                [
                    [g, r, f, _maybe(er)]
                    for g, r, f, er in zip(
                        s["study"]["gammas"],
                        truth["rate"],
                        truth["failures"],
                        truth["estimate_recall"],
                        strict=True,
                    )
                ],
            )
        ),
    ]
    if "rate_truth" in figures:
        parts.append(_img(figures["rate_truth"], "estimate against the true rate"))
    if "recall" in figures:
        parts.append(_img(figures["recall"], "retention-recall per batch (ground truth)"))
    parts.append("</section>")
    return parts


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
    if v is None:
        return ""
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
        f"Pool of {s['study']['pool_size']} segments; {len(s['batches'])} "
        f"batch{'' if len(s['batches']) == 1 else 'es'}; "
        f"{spent['count']} simulations costing {spent['cost']:g} level-0 runs"
        + (
            f" ({spent['superseded']} of those results superseded by a later "
            "`ingest-results --replace`, kept in the log)."
            if spent.get("superseded")
            else "."
        )
    )
    lines.append("")
    lines += [spend_line(s), ""]
    found = s["failures_found"]
    lines += [
        f"Failures found: {found['count']} ({found['confirmed']} confirmed at level 0 at "
        f"the largest gamma, {max(s['study']['gammas']):g}, "
        f"{found['leads']} lead{'s' if found['leads'] != 1 else ''} seen only at a cheap level), "
        "every one in report/failures.csv.",
        "",
    ]
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
        # With --truth the mean is of the true level-0 values of every pick, not of the
        # level-0 runs: the column says so, as the page's does.
        of = "mean level-0 f of picks (ground truth)" if s["truth"] else "mean level-0 f"
        lines += [
            f"| batch | strategy | picks | cost | {of} (SE) | pending | abandoned |",
            "|---|---|---|---|---|---|---|",
        ]
        for b in s["batches"]:
            se = b["mean_f0_se"]  # None below two level-0 values: no SE, not "()"
            mf = (
                ""
                if b["mean_f0"] is None
                else f"{b['mean_f0']:.3g}" + ("" if se is None else f" ({se:.2g})")
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
            "Diverse likely failures (level-0 value unknown; likely and unlike each other, "
            "in the order chosen, not by p_n): "
            + ", ".join(f"{r['segment_id']} (p_n {r['p_n']:.2g})" for r in s["diverse_failures"])
            + "."
        )
    lines.append("")
    lines += group_lines(s["groups"])
    if s.get("truth"):
        t = s["truth"]
        lines.append(
            "**Against ground truth (--truth; a real study has none):** true rate "
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
            "| batch | cost per level | confirmed (so far) | expected before results | model's rate (sd bound) | J before -> after | J decrease per cost |",
            "|---|---|---|---|---|---|---|",
        ]
        for t in trends:
            rate = "" if t["gp_rate"] is None else f"{t['gp_rate']:.3g} ({t['gp_sd_bound']:.2g})"
            j = "" if t["j_before"] is None else f"{t['j_before']:.3g} -> {t['j_after']:.3g}"
            dj = "" if t["j_decrease_per_cost"] is None else f"{t['j_decrease_per_cost']:.3g}"
            cost = ", ".join(f"{k}: {v:g}" for k, v in t["cost_per_level"].items())
            exp = (
                ""
                if t["predicted_failures"] is None
                else f"{t['predicted_failures']:.2g} ± {t['predicted_sd']:.2g}"
            )
            lines.append(
                f"| {t['batch']} | {cost} | {t['confirmed']} ({t['confirmed_so_far']}) | {exp} | {rate} | {j} | {dj} |"
            )
        lines.append("")
    if summary["predicted_vs_found"] is not None:
        lines += [predicted_line(summary["predicted_vs_found"]), ""]
    history = summary["estimate_history"]
    if len(history) > 1:
        lines += [
            "| plan | after batch | design | K | p_hat | interval |",
            "|---|---|---|---|---|---|",
        ]
        for h in history:
            kind = h.get("interval", "gamma")
            lines.append(
                f"| {h['plan']} | {h.get('after_batch', '')} | {h['design']} | {h['samples_K']:g} "
                f"| {h['p_hat']:.3g} | {100 * h['confidence']:g}% {kind}: "
                f"[{h['ci_low']:.3g}, {h['ci_high']:.3g}] |"
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


def spend_line(summary: dict[str, Any]) -> str:
    """Discovery spend apart from estimate-plan spend, in one sentence (summary.md)."""
    sp = summary["spend"]

    def part(d: dict[str, Any]) -> str:
        levels = ", ".join(
            f"level {lv}: {v['count']}" for lv, v in d["per_level"].items() if v["count"]
        )
        return f"{d['count']} runs costing {d['cost']:.3g}" + (f" ({levels})" if levels else "")

    text = f"Spend (results in): discovery batches {part(sp['discovery'])}; estimate plans "
    text += part(sp["estimate"])
    if sp["plans"]:
        text += ", by plan " + ", ".join(f"{p['plan']}: {p['count']}" for p in sp["plans"])
    if sp["other"]["count"]:
        text += f"; results not asked for {part(sp['other'])}"
    return text + "."


def predicted_line(pv: dict[str, Any]) -> str:
    """The failures found against what the model predicted before the results."""
    b = pv["batches"]
    which = f"batch {b[0]}" if len(b) == 1 else f"batches {', '.join(map(str, b[:-1]))} and {b[-1]}"
    return (
        f"Before their results, the model expected {pv['predicted']:.2g} ± "
        f"{pv['predicted_sd']:.2g} level-0 failures among the {pv['level0_results']} level-0 "
        f"results of {which}; {pv['found']} {'was' if pv['found'] == 1 else 'were'} found"
        + (
            " (more than 2 sd above: the model misses failures)."
            if pv["found"] > pv["predicted"] + 2 * pv["predicted_sd"]
            else "."
        )
    )


def group_lines(groups: dict[str, Any] | None) -> list[str]:
    """The per-cluster or per-tag breakdown as a Markdown table (summary.md)."""
    if groups is None or not groups["rows"]:
        return []
    levels = sorted(groups["rows"][0]["runs_per_level"], key=int)
    lines = [
        f"By {groups['by']}: {groups['how']}.",
        *([f"**{groups['caveat']}.**"] if groups.get("caveat") else []),
        "",
        f"| {groups['by']} | segments | expected failures | "
        + " | ".join(f"level {lv} runs" for lv in levels)
        + " | confirmed | leads |",
        "|---" * (5 + len(levels)) + "|",
    ]
    for r in groups["rows"]:
        lines.append(
            f"| {r['group']} | {r['size']} | {_na(r['expected_failures'], '.3g')} | "
            + " | ".join(str(r["runs_per_level"][lv]) for lv in levels)
            + f" | {r['confirmed']} | {r['leads']} |"
        )
    return [*lines, ""]
