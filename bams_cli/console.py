"""Everything the user sees: rich tables, progress bars, one-line errors."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

from rich.console import Console, ConsoleDimensions
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

#: Width of a console that is not a terminal (a CI log, a pipe, a file): wide enough that
#: no line of ours wraps, since a log viewer wraps (or scrolls) on its own.
PIPE_WIDTH = 10_000


class _Console(Console):
    """A rich Console that does not wrap when it is not writing to a terminal.

    Rich falls back to 80 columns when stdout is a pipe, so a long path in a table or a
    sentence broke into pieces in CI logs. Tables do not expand, so a wide console only
    stops the wrapping; on a terminal the terminal's width still rules.
    """

    @property
    def size(self) -> ConsoleDimensions:
        real = super().size
        return real if self.is_terminal else ConsoleDimensions(PIPE_WIDTH, real.height)

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        Console.size.fset(self, new_size)  # type: ignore[attr-defined]


out = _Console()
err = _Console(stderr=True, highlight=False, soft_wrap=True)


class _Mode:
    """How this command prints: ``quiet`` (errors only) and ``json`` (errors as JSON)."""

    quiet = False
    json = False


mode = _Mode()


def set_mode(*, quiet: bool, json_out: bool) -> None:
    """``--quiet``: nothing on stdout or stderr but errors (and ``--json`` output, which
    was asked for); ``--json``: errors and warnings as one JSON object per stderr line."""
    mode.quiet, mode.json = quiet, json_out
    out.quiet = quiet


def error(message: str, exit_code: int = 1) -> None:
    """One line on stderr: what failed, expected vs got, and the fix.

    Under ``--json`` the line is a JSON object, ``{"error": ..., "exit_code": ...}``, so a
    script reads the failure as it reads the output.
    """
    if mode.json:
        sys.stderr.write(json.dumps({"error": message, "exit_code": exit_code}) + "\n")
        return
    # The message is data (it quotes file contents), never markup: "[[levels]]" or a
    # segment id like "[/a]" must print as written.
    err.print(Text.assemble(("error:", "bold red"), " ", message))


def warning(message: str) -> None:
    """One line on stderr (a JSON object under ``--json``); nothing under ``--quiet``."""
    if mode.quiet:
        return
    if mode.json:
        sys.stderr.write(json.dumps({"warning": message}) + "\n")
        return
    err.print(f"warning: {message}", markup=False)


def note(message: str) -> None:
    if not mode.quiet:
        err.print(message, markup=False)


def print_json(summary: Mapping[str, Any]) -> None:
    # allow_nan=False: a bare NaN/Infinity is not JSON; an undefined number must be null.
    sys.stdout.write(json.dumps(summary, indent=2, default=str, allow_nan=False) + "\n")


def rows_table(
    title: str, columns: list[str], rows: list[list[Any]], total: int | None = None
) -> None:
    """A table of ``rows``; with ``total`` above their count, its caption says how many
    more there are (the summaries list the first 20)."""
    more = (total or 0) - len(rows)
    caption = f"... and {more:,} more (first {len(rows)} shown)" if more > 0 else None
    table = Table(title=title, title_justify="left", caption=caption, caption_justify="left")
    for col in columns:
        table.add_column(
            col, justify="right" if col not in {"segment_id", "name", "level"} else "left"
        )
    for row in rows:
        table.add_row(*[Text(f"{v:.6g}" if isinstance(v, float) else str(v)) for v in row])
    out.print(table)


def model_checks(checks: Mapping[str, Any], transform: Mapping[str, Any] | None = None) -> None:
    """One line per self-check of a fitted model (``core.gp.checks``), and its transform."""
    if transform and transform.get("kind") == "asinh":
        out.print(
            f"model: g(y) = {transform['centre']:.4g} + s asinh((y - {transform['centre']:.4g})"
            f" / s), s = {transform['scale']:.4g} (the metric compressed far from gamma; "
            "scales above are in g's units)",
            highlight=False,
        )
    loo = checks["loo_level0"]
    if loo["n"]:
        of = int(loo.get("of") or loo["n"])
        runs = (
            plural(loo["n"], "level-0 run")
            if of <= loo["n"]
            else (f"{loo['n']} of the {of:,} level-0 runs (a random sample)")
        )
        out.print(
            f"check: leave-one-out at {runs}, mean z^2 {loo['mean_z2']:.2f} (1 if calibrated)",
            highlight=False,
        )
    for pair in checks["pairs"]:
        if pair["n_pairs"] >= 2:
            out.print(
                f"check: {pair['n_pairs']} segments run at levels 0 and {pair['level']}: "
                f"sd(y{pair['level']} - y0) {pair['sd_observed']:.3g}, model "
                f"{pair['sd_fitted']:.3g}",
                highlight=False,
            )


def study_status(s: Mapping[str, Any]) -> None:
    """``bams-cli status``: batches, plans, model, latest estimate, then the next command."""
    pool = "no pool yet" if s["pool_size"] is None else f"{s['pool_size']} segments"
    out.print(
        f"study {s['workspace']}: {pool}, levels {', '.join(s['levels'])}, "
        f"gammas {', '.join(f'{g:g}' for g in s['gammas'])}, {s['observations']} results",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    if s["batches"]:
        rows_table(
            "batches",
            ["batch", "strategy", "picks", "cost", "pending", "abandoned", "hand-off"],
            [
                [
                    b["batch"],
                    b["strategy"],
                    b["picks"],
                    b["cost"],
                    b["pending"],
                    b.get("abandoned", 0),
                    b["handoff"],
                ]
                for b in s["batches"]
            ],
        )
    if s["plans"]:
        rows_table(
            "estimate plans",
            ["plan", "sampled", "pending", "abandoned", "hand-off", "estimate"],
            [
                [
                    p["plan"],
                    p["sampled"],
                    p["pending"],
                    p.get("abandoned", 0),
                    p["handoff"],
                    p["estimate"] or "-",
                ]
                for p in s["plans"]
            ],
        )
    m = s["model"]
    if m is None:
        text = "none yet"
    elif m["fresh"]:
        text = f"up to date (fitted on {m['fitted_on']} results at {m['fitted_at']})"
    else:
        text = f"stale: {m['reason']}"
    out.print(f"model: {text}", markup=False, highlight=False, soft_wrap=True)
    if s["latest_estimate"] is not None:
        estimate_lines(s["latest_estimate"])
    if s["commit_in_progress"]:
        note(
            "note: a command's commit is in progress or was interrupted; the next command completes it"
        )
    out.print(Text.assemble(("next: ", "bold"), s["next"]["text"]), soft_wrap=True)


def estimate_lines(e: Mapping[str, Any]) -> None:
    """The latest estimate's headline, one line per gamma (``status``, ``loop``):
    ``estimate (plan 2): gamma 0.56: p_hat 0.012, 90% interval [0.0009, 0.074]``."""
    done, planned = e.get("stages_done", 1), e.get("stages", 1)
    of = f", stage {done} of {planned} only" if done < planned else ""
    if e.get("out_of_date"):  # a result it read was replaced since: `estimate` again
        of += ", out of date"
    for row in e["estimates"]:
        rate = (
            f"p_hat between {row['p_hat_low']:.4g} and {row['p_hat_high']:.4g} (abandoned "
            "segments passing, then failing)"
            if "p_hat_high" in row
            else f"p_hat {row['p_hat']:.4g}"
        )
        out.print(
            f"estimate (plan {e['plan']}{of}): gamma {row['gamma']:g}: {rate}, "
            f"{round(100 * row['confidence'])}% interval [{row['ci_low']:.4g}, "
            f"{row['ci_high']:.4g}]",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


#: A command quicker than this prints no progress lines in a log (seconds).
PLAIN_AFTER_S = 3.0
#: At most one progress line per phase this often in a log (seconds).
PLAIN_EVERY_S = 30.0


def plain_progress(
    label: str,
    *,
    after_s: float = PLAIN_AFTER_S,
    every_s: float = PLAIN_EVERY_S,
    clock: Callable[[], float] = time.monotonic,
) -> Callable[[str, int, int], None]:
    """A ``progress(phase, done, total)`` callback for logs: a few plain lines, no bar.

    Nothing for a command that ends within ``after_s``; after that, one line when a phase
    is first seen (a one-step phase: when it ends), at most one per ``every_s`` while it runs (with a linear ETA), and one
    when it ends, e.g. ``select: greedy 4/6, 12 s elapsed, about 6 s left``.
    """
    start = clock()
    began: dict[str, float] = {}
    printed: dict[str, tuple[float, bool]] = {}  # phase -> (when, whether it was the end)

    def update(phase: str, done: int, total: int) -> None:
        now = clock()
        began.setdefault(phase, now)
        if mode.quiet or now - start < after_s:
            return
        finished = total > 0 and done >= total
        if total <= 1 and not finished:  # a one-step phase says only when it is done
            return
        last = printed.get(phase)
        if last is not None and (last[1] or (not finished and now - last[0] < every_s)):
            return
        printed[phase] = (now, finished)
        # "fit: 1/1", not "fit: fit: 1/1", when the phase is the command's own name.
        head = label if label and label.rstrip(": ") == phase else f"{label}{phase}: "
        line = f"{head}{done}/{total}, {now - start:.0f} s elapsed"
        ran = now - began[phase]
        if not finished and done > 0 and ran > 0:
            line += f", about {ran * (total - done) / done:.0f} s left"
        err.print(line, markup=False, highlight=False)

    return update


@contextmanager
def progress(
    enabled: bool = True, label: str = ""
) -> Iterator[Callable[[str, int, int], None] | None]:
    """A ``progress(phase, done, total)`` callback: one rich bar per phase, with its ETA, on
    a terminal; a few plain lines in a log (``plain_progress``); nothing when disabled
    (``--json``) or under ``--quiet``."""
    if not enabled or mode.quiet:
        yield None
        return
    if not err.is_terminal:
        yield plain_progress(f"{label}: " if label else "")
        return
    bars = Progress(
        TextColumn("{task.description:<14}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=err,
        transient=True,
    )
    tasks: dict[str, Any] = {}

    def update(phase: str, done: int, total: int) -> None:
        if phase not in tasks:
            tasks[phase] = bars.add_task(phase, total=total)
        bars.update(tasks[phase], completed=done, total=total)

    with bars:
        yield update


@contextmanager
def loop_progress(enabled: bool = True) -> Iterator[Callable[[str, int, int], None]]:
    """``bams-cli loop``: one line per step on stderr, and a bar of lists done on a terminal."""
    if not enabled or mode.quiet:
        yield lambda *_: None
        return
    bars = None
    if err.is_terminal:
        bars = Progress(
            TextColumn("{task.description:<30}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=err,
            transient=True,
        )
    task = bars.add_task("loop", total=1) if bars is not None else None

    def update(step: str, done: int, total: int) -> None:
        if bars is not None and task is not None:
            bars.update(task, description=step, completed=done, total=total)
        if step != "done":
            err.print(f"loop [{done}/{total}]: {step}", markup=False, highlight=False)

    if bars is None:
        yield update
        return
    with bars:
        yield update


# --- short human summaries: the key facts of each command; --json has every detail ---


def _gamma(g: Any) -> str:
    """A threshold as the study set it (1.349 is not "1.35"): ``:g`` as elsewhere."""
    return "n/a" if g is None else f"{float(g):g}"


def _num(x: Any, digits: int = 3) -> str:
    """A number for a summary line: ``0.00413`` -> ``0.00413``, ``None`` -> ``n/a``."""
    if x is None:
        return "n/a"
    if isinstance(x, int):
        return str(x)
    return f"{float(x):.{digits}g}"


def plural(n: int, word: str, plural: str | None = None) -> str:
    """``n`` and ``word``, plural unless n is 1: "1 row", "2 rows"."""
    return f"{n} {word if n == 1 else plural or word + 's'}"


def facts(headline: str, rows: Mapping[str, Any] | None = None) -> None:
    """A headline, then ``key  value`` lines aligned on the values; empty values are left
    out. Printed as data (no markup), and never wrapped in a log."""
    out.print(headline, markup=False, highlight=False, soft_wrap=True)
    shown = {k: str(v) for k, v in (rows or {}).items() if v not in (None, "", [], {})}
    width = max((len(k) for k in shown), default=0)
    for key, value in shown.items():
        out.print(f"  {key:<{width}}  {value}", markup=False, highlight=False, soft_wrap=True)


def init_summary(s: Mapping[str, Any]) -> None:
    levels = ", ".join(f"{lv['name']} (cost {lv['cost']:g})" for lv in s["levels"])
    facts(
        f"workspace {s['workspace']} created",
        {
            "settings": s["settings"],
            "gammas": ", ".join(f"{g:g}" for g in s["gammas"]),
            "levels": levels,
            "seed": s.get("seed"),
            "dimension": s.get("embedding_dim"),
        },
    )
    for text in s.get("warnings") or []:
        warning(text)


def embed_reduce_summary(s: Mapping[str, Any]) -> None:
    if s.get("unchanged"):
        facts(f"{s['segments']}: {s['pool_size']} segments; {s.get('note', 'nothing changed')}")
        return
    errors = s.get("reconstruction_error") or {}
    facts(
        f"pool {s['segments']}: {s['pool_size']} segments ({s['added']} added), "
        f"{s['method']} {s['input_dim']} -> {s['dim']} dimensions",
        {
            "dimensions": s.get("dim_choice") and f"{s['dim']}, chosen: {s['dim_choice']}",
            "reconstruction error": ", ".join(f"{k} {_num(v)}" for k, v in errors.items()),
            "pass-through": ", ".join(s.get("passthrough_columns") or []),
        },
    )
    for text in s.get("warnings") or []:
        warning(text)


def ingest_summary(s: Mapping[str, Any]) -> None:
    names = s.get("level_names") or []
    by_level = ", ".join(
        f"level {lv}{f' ({names[int(lv)]})' if int(lv) < len(names) else ''}: {n}"
        for lv, n in (s.get("by_fidelity") or {}).items()
    )
    active = s.get("log_active", s["log_rows"])
    # Rows superseded by --replace, this time or before: inactive, kept in the log.
    kept = s["log_rows"] - active
    facts(
        f"ingested {plural(s['ingested'], 'result')} into {s['observations']} "
        f"({plural(active, 'row')} now{f', {kept} superseded kept beside them' if kept else ''})",
        {
            "by level": by_level,
            "replaced": s["replaced"] or None,
            "already known": s["already_known"] or None,
        },
    )


def pending_lists(lists: list[Mapping[str, Any]]) -> None:
    """One line per batch or plan partly answered: the list of its pending requests alone,
    the one to simulate (``state.pending``)."""
    for e in lists:
        if e.get("pending_handoff"):
            gone = int(e.get("abandoned") or 0)
            answered = int(e["requests"]) - int(e["pending"]) - gone
            others = (
                "the others have results"
                if not gone
                else "the others were abandoned"
                if not answered
                else f"of the others {answered} {'has' if answered == 1 else 'have'} "
                f"results, {gone} {'was' if gone == 1 else 'were'} abandoned"
            )
            out.print(
                f"{e['list']}: {e['pending']} of its {e['requests']} requests still await "
                f"results; simulate {e['pending_handoff']}, which lists them alone ({others})",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )


def simulate_summary(s: Mapping[str, Any]) -> None:
    facts(f"wrote {s['results']}: {plural(s['rows'], 'result')}; {s['note']}")


def fit_summary(s: Mapping[str, Any]) -> None:
    """Fitted-on counts, the GP's own rate, one line per level (lengthscales as a range),
    the model's self-checks and warnings."""
    per_level = s["n_observations_per_level"]
    counts = ", ".join(f"level {lv}: {n}" for lv, n in enumerate(per_level))
    rate = ", ".join(f"gamma {g}: {_num(p)}" for g, p in (s.get("gp_rate_estimate") or {}).items())
    hp = s["hyperparameters"]

    def ells(xs: list[float]) -> str:
        if len(xs) == 1:
            return _num(xs[0])
        return f"{_num(min(xs))} .. {_num(max(xs))} over {len(xs)} dimensions"

    failed = s.get("level0_failures") or {}
    if failed and not any(failed.values()):
        rate += " (the model's own mean p_n; no level-0 failure has checked it yet)"
    rows: dict[str, Any] = {
        "GP rate estimate": rate,
        "level 0": f"output sd {_num(hp['outputscale0'] ** 0.5)}, noise sd "
        f"{_num(hp['noise'][0] ** 0.5)}, lengthscales {ells(hp['lengthscales0'])}",
    }
    for lv, (scale, ell) in enumerate(zip(hp["outputscales"], hp["lengthscales"], strict=True), 1):
        rho = float((hp.get("scales") or [1.0] * len(hp["outputscales"]))[lv - 1])
        rows[f"level {lv}"] = (
            (f"{_num(rho)} x level 0 (scale), " if rho != 1.0 else "")
            + f"discrepancy sd {_num(scale**0.5)}, noise sd {_num(hp['noise'][lv] ** 0.5)}, "
            f"lengthscales {ells(ell)}"
        ) + (f" (no level-{lv} result yet: no data fitted these)" if not per_level[lv] else "")
    if s.get("conditioning"):
        rows["conditioning"] = s["conditioning"]["note"]
    if (s.get("scoring") or {}).get("method") == "bounded":
        rows["scoring"] = s["scoring"]["note"]
    rows["files"] = f"{s['model']}, {s['scores']}"
    facts(f"model fitted on {plural(s['observations'], 'result')} ({counts})", rows)
    model_checks(s["checks"], s.get("transform"))
    for warning_text in s.get("warnings") or []:
        warning(warning_text)


def select_summary(s: Mapping[str, Any]) -> None:
    per_level = {int(k): v for k, v in (s.get("picks_per_level") or {}).items()}
    level0 = per_level.get(0, 0)
    cheap = sum(v for k, v in per_level.items() if k > 0)
    split = f"{level0} level-0, {cheap} cheap" if cheap else f"{level0} level-0"
    head = f"batch {s['batch']}: {plural(s['picks'], 'pick')} ({split}), strategy {s['strategy']}"
    if s.get("unchanged"):
        head += " (already made with these options; nothing changed)"
    j = None
    if s.get("j_before") is not None and s.get("j_after") is not None:
        j = f"{_num(s['j_before'])} -> {_num(s['j_after'])}"
    confirm = None
    if s.get("confirm_picks"):
        confirm = (
            f"{plural(s['confirm_picks'], 'level-0 run')} ({s.get('confirm_leads', 0)} of "
            "cheap-level leads)"
        )
    total = (s.get("timings_s") or {}).get("total")
    facts(
        head,
        {
            "cost": f"{_num(s['total_cost'])} of budget {_num(s['budget'])}",
            "J": j,
            "confirming": confirm,
            "hand-off": s.get("handoff_csv") or s.get("handoff"),
            "results template": s.get("results_template"),
            # The selection's own time: the progress display's elapsed also counts reading
            # the pool and scores and writing the batch.
            "time": None if total is None else f"{total:.1f} s selecting",
        },
    )
    for text in s.get("warnings") or []:
        warning(text)


def _stage_weights(w: Sequence[float] | None) -> str | None:
    """A staged plan's weights in the combined estimate (None for one stage)."""
    if not w or len(w) < 2:
        return None
    return f"{' / '.join(f'{x:.3g}' for x in w)} in the combined estimate, fixed at stage 1"


def _plan_budget(s: Mapping[str, Any]) -> str:
    """A plan's K: this stage's expected level-0 runs, and the whole estimate's where it
    runs in stages."""
    if (s.get("stages") or 1) > 1:
        return (
            f"K {_num(s['samples_K'])} this stage, of {_num(s['series_K'])} over the "
            f"estimate's {s['stages']} stages"
        )
    return f"K {_num(s['samples_K'])} of {_num(s['series_K'])} for the estimate"


def plan_summary(s: Mapping[str, Any]) -> None:
    head = (
        f"estimate plan {s['plan']} (stage {s['stage']} of {s['stages']}): "
        f"{plural(s['to_simulate'], 'segment')} to simulate at level 0"
    )
    facts(
        head,
        {
            "budget": _plan_budget(s),
            "stage weights": _stage_weights(s.get("stage_weights")),
            "design": f"{s['design']}, weighting {s['weighting']}",
            "known stratum": f"{plural(s['known_stratum'], 'segment')} with a level-0 result",
            # The plan is drawn for the largest gamma, whose failures hold every other's.
            "GP rate estimate": f"{_num(s.get('gp_rate_estimate'))} at gamma "
            f"{_gamma(s.get('plan_gamma'))}, the largest, which the plan is drawn for",
            "trust in p_n": _trust(s.get("model_check")),
            "confirmation": _confirm_prior((s.get("screen") or {}).get("confirm_prior")),
            "screen leads": _screen_leads(s.get("screen")),
            "hand-off": s["handoff"],
            "results template": s.get("results_template"),
        },
    )
    for text in s.get("notes") or []:
        note(text)
    for text in s.get("warnings") or []:
        warning(text)


def _trust(check: Mapping[str, Any] | None) -> str | None:
    """The plan's model check in one line: the share of failures p_n does not explain (lam)
    and what it rests on (``core.design.RiskPosterior.summary``)."""
    if not check or check.get("lam") is None:
        return None
    prior = check.get("prior")
    return (
        f"{check['lam']:.2f} of the failure mass unexplained by p_n (up to "
        f"{check['lam_high']:.2f}), from {plural(check['failures'], 'failure')} in "
        f"{plural(check['sampled'], 'run')} of earlier estimate stages"
        + (f"; prior Beta({prior[0]:g}, {prior[1]:g})" if prior else "")
    )


def _confirm_prior(prior: Any) -> str | None:
    """A screen's confirmation: the prior its pi2 was planned under (the trust line above
    is the interval's allowance's)."""
    if not prior:
        return None
    return (
        f"pi2 within the screen planned under Beta({prior[0]:g}, {prior[1]:g}), as the "
        "screen recorded; the trust above prices the interval's allowance"
    )


def _screen_leads(screen: Mapping[str, Any] | None) -> str | None:
    """A screen's confirmation: how many of its lowest cheap results it runs for certain."""
    if not screen or screen.get("screen_leads") is None:
        return None
    return (
        f"the screen's {plural(screen['screen_leads'], 'lowest cheap result')} confirmed "
        f"with certainty, of {_num(screen['level0_budget'])} level-0 runs"
    )


def screen_summary(s: Mapping[str, Any]) -> None:
    head = (
        f"screen for estimate plan {s['plan']}: {plural(s['cheap_runs'], 'segment')} to "
        f"simulate at level {s['screen_level']}"
    )
    facts(
        head,
        {
            "budget": f"K {_num(s['samples_K'])}: share {_num(s['screen_share'])} on the screen "
            f"at cost {_num(s['screen_cost'])} a run, about {_num(s['level0_left'])} left "
            "for level 0",
            "screened": f"{plural(s['screened'], 'segment')} ({s['cheap_in_log']} with a cheap "
            f"result in the log, {s['cheap_abandoned']} abandoned at that level"
            + (
                f"; {plural(s['leads_certain'], 'open lead')} screened and confirmed with "
                "certainty)"
                if s.get("leads_certain")
                else ")"
            ),
            "design": s["screen_design"],
            "known stratum": f"{plural(s['known_stratum'], 'segment')} with a level-0 result",
            "screen file": s["screen_file"],
            "hand-off": s.get("handoff") or "none: nothing to run",
            "results template": s.get("results_template"),
        },
    )
    for text in s.get("notes") or []:
        note(text)
    for text in s.get("warnings") or []:
        warning(text)


def report_summary(s: Mapping[str, Any]) -> None:
    rates = "; ".join(
        f"gamma {e['gamma']:g}: {_num(e['p_hat'])} [{_num(e['ci_low'])}, {_num(e['ci_high'])}]"
        for e in s.get("estimates") or []
    )
    facts(
        f"report {s['report']}",
        {
            "summary": f"{s['summary_md']}, {s['summary_json']}",
            "failure rate": rates or "no estimate yet",
            "figures": len(s.get("figures") or []),
        },
    )
    for text in s.get("notices") or []:
        note(f"notice: {text}")


def loop_summary(s: Mapping[str, Any]) -> None:
    facts(
        f"loop: {plural(len(s['steps']), 'step')}; the study has "
        f"{plural(s['batches'], 'batch', 'batches')} and {plural(s['plans'], 'estimate plan')}",
        {"results": s["results_dir"], "estimate": s.get("estimate_file")},
    )
    if s.get("estimate"):
        estimate_lines(s["estimate"])
