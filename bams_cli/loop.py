"""``bams-cli loop``: the discovery loop against the user's own simulator, resumable.

Every pass reads the workspace and takes the one step the study needs next, so a loop
killed at any point picks up where it stopped and a finished loop does nothing:

- picks await results, and their results file is in ``--results-dir``: ingest it;
- picks await results, no results file yet: run the simulator on the hand-off list. It
  writes to a temporary name that is renamed to the results file only once the command
  exits 0, so a killed simulator never leaves a half-written file that looks finished;
- fewer than ``batches`` discovery batches (a screen's batch of cheap runs is the
  estimate's and does not count): a random first batch, or ``fit`` (skipped when the model
  is up to date) then ``select --batch N``; refused while a screen awaits its confirmation;
- with ``then_estimate``: ``estimate --plan``, its simulation and ingest, ``estimate``;
- last, ``fit`` when the model is older than the results.

Each step is the command a user would run (the same pipeline function, holding the
workspace lock and writing atomically); the loop itself writes nothing else but the
simulator's results files, the pending-only list it hands the simulator, and a note of the
running simulator (``.simulator-NAME.json``). One loop drives a workspace at a time: it
holds a second lock (``LOOP_LOCK_FILE``) for its whole run, so a second loop started beside it is refused
naming the first (or waits for it with ``--wait``) instead of simulating the same list
twice; a loop that was killed leaves no lock behind.

The simulator (it may be a script that starts more processes) stays in the loop's process
group, so whatever stops the whole job (Ctrl-C in a terminal, ``kill -- -PGID``, a CI
runner's timeout) reaches it too. A loop stopped alone by SIGTERM, SIGINT or SIGHUP ends
the simulator and every process it started (SIGTERM, then SIGKILL after
``SIMULATOR_GRACE_S``), discards the partial results and exits 128 + the signal's number;
the list stays pending, so the same loop run again resumes it. A SIGKILL of the loop alone
cannot be caught: it leaves the simulator running, and a loop started while it still runs
refuses to simulate the same list again, naming its pids. Before starting the simulator
the loop notes, in ``.simulator-NAME.json`` beside the results file, a token it puts in the
simulator's environment (``SIMULATOR_TOKEN_ENV``), which every process the simulator starts
inherits: a loop killed at any instant, even before it learned the simulator's pid, leaves
a note that finds the whole tree.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bams_cli import abandon, defaults, memory, pipeline, stopping
from bams_cli.errors import BamsError, InputError, OptionValueError, WorkspaceError
from bams_cli.pipeline._common import (
    check_budget,
    check_buys_a_run,
    check_clusters,
    check_samples,
    check_workers,
)
from bams_cli.pipeline.screening import check_share, open_screen, screen_path
from bams_cli.state import pending, schemas
from bams_cli.state.handoff import Kind, handoff_path, pending_path
from bams_cli.state.io import read_metadata_json, transaction
from bams_cli.state.lock import LOOP_LOCK_FILE, workspace_lock
from bams_cli.state.workspace import Workspace
from bams_cli.status import latest_estimate

#: ``on_step(description, done, total)``: what the loop is doing, for a progress display.
OnStep = Callable[[str, int, int], None]

#: Signals that stop a loop and its simulator: kill's default, Ctrl-C, a closed terminal.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
#: Seconds a stopped simulator's processes have to exit after SIGTERM before SIGKILL.
SIMULATOR_GRACE_S = 5.0


class LoopError(BamsError):
    """The loop cannot go on by itself (a simulator that failed, results still missing)."""


class SimulatorFailed(LoopError):
    """The simulator exited non-zero on a list: ``what`` says how, ``returncode``."""

    def __init__(self, what: str, returncode: int, retries: int = 0) -> None:
        tries = f", its --retries {retries} spent" if retries else ""
        super().__init__(
            f"{what}{tries}; fix it and run the same `bams-cli loop` again (it resumes here)"
        )
        self.what, self.returncode = what, returncode


class LoopStopped(stopping.Stopped):
    """A signal stopped the loop; ``exit_code`` is 128 + its number, as a shell reports it."""


@dataclass(frozen=True)
class Options:
    simulator: str
    batches: int
    budget: float
    first_budget: float
    then_estimate: bool
    samples: float | None
    results_dir: Path
    abandon_failed: bool
    retries: int
    clusters: int
    workers: int | None
    wait: bool
    screen: float | str | None = None  # with then_estimate: a screen's share of K, or "auto"


def loop(
    root: Path,
    *,
    simulator: str,
    batches: int,
    budget: float = defaults.BUDGET,
    first_budget: float | None = None,
    then_estimate: bool = False,
    samples: float | None = None,
    screen: float | str | None = None,
    results_dir: Path | None = None,
    abandon_failed: bool = False,
    retries: int = defaults.RETRIES,
    clusters: int = 6,
    workers: int | None = None,
    wait: bool = False,
    on_step: OnStep | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the discovery loop against a simulator: fit, select, simulate, ingest.

    Runs until the study has ``batches`` batches with results (and, with
    ``then_estimate``, an estimate), taking each step the workspace says is next: a loop
    that was killed resumes where it stopped, and a finished one does nothing
    (``unchanged``). Each step is the command one would run by hand; the simulator's
    results land in ``results_dir`` only when it exits 0. One loop drives a workspace at a
    time.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    simulator : str
        Shell command answering a hand-off list: ``{handoff}`` is the list (CSV) to read,
        ``{results}`` the results file (CSV) to write.
    batches : int
        Discovery batches the study should have (the first random; a screen's batch of
        cheap runs belongs to the estimate and does not count).
    budget : float, default ``defaults.BUDGET``
        Budget of each BAMS batch (cost units).
    first_budget : float, optional
        Budget of the random first batch (default: ``budget``).
    then_estimate : bool, default False
        Then plan the rate estimate, simulate it and compute it.
    samples : float, optional
        With ``then_estimate``: the estimate's budget K.
    screen : float, "auto" or "off", optional
        With ``then_estimate``: a screened estimate (``estimate --plan --screen``): this
        share of K on cheap-level runs first, their results and a refit, then the level-0
        confirmation; "auto" as ``estimate --plan --screen auto`` decides; "off" plans the
        staged estimate. Default ``defaults.SCREEN``.
    results_dir : Path, optional
        Where the simulator's results files go (default: ``root / "loop-results"``).
    abandon_failed : bool, default False
        Record results rows with a failed status as abandoned and go on (and estimate
        with ``failed_as="bounds"``); with ``retries``, only once they are spent.
    retries : int, default ``defaults.RETRIES`` (0)
        Times the simulator is run again on a list's requests still without a result
        (failed or missing rows) before the loop stops (or abandons them); the results file
        of each try is kept as ``retried-K-NAME.csv``.
    clusters : int, default 6
        select's clusters S.
    workers : int, optional
        select's local worker processes.
    wait : bool, default False
        Wait for another loop, or another command's workspace lock, instead of failing.
    on_step : callable ``(description, done, total) -> None``, optional
        Called before each step with what the loop is doing (the CLI draws its progress
        with it).
    on_warning : callable ``(text) -> None``, optional
        Called with each warning a step gives (fit's self-checks, select's, the estimate
        plan's), prefixed with the step, as the step ends: run by hand, each command
        prints its own.

    Returns
    -------
    dict
        The summary ``--json`` prints: ``workspace``, ``batches`` (discovery batches,
        as ``batches`` counts them: a screen's is not one), ``plans``, ``steps``
        (each step taken), ``unchanged``, ``results_dir``, ``estimate_file`` and
        ``estimate`` (the latest estimate's headline, as ``status`` gives it: per gamma
        p_hat and its interval), null before any estimate.

    Raises
    ------
    LoopError
        The simulator failed or wrote no results, or results are still missing after it.
    LoopStopped
        SIGTERM, SIGINT or SIGHUP stopped the loop (its simulator ended, the list still
        pending); a ``KeyboardInterrupt``.
    OptionValueError
        ``simulator`` does not name ``{handoff}`` and ``{results}``, or ``batches``, a
        budget, ``samples``, ``clusters`` or ``workers`` out of range, before any step;
        exit code 2.
    BamsError
        Any step's own error, as that command raises it.
    """
    if "{handoff}" not in simulator or "{results}" not in simulator:
        raise OptionValueError(
            f"--simulator {simulator!r}: must name {{handoff}} (the hand-off list to read) "
            "and {results} (the results file to write), e.g. 'my-sim {handoff} -o {results}'"
        )
    if batches < 1:
        raise OptionValueError(f"--batches {batches}: must be >= 1")
    if retries < 0:
        raise OptionValueError(f"--retries {retries}: must be >= 0")
    # Checked before any step: the estimate's --samples would otherwise be refused only
    # after every batch had been simulated.
    check_budget(budget)
    if first_budget is not None:
        check_budget(first_budget, "--first-budget")
    check_samples(samples)
    check_clusters(clusters)
    check_workers(workers)
    ws = Workspace(Path(root))
    settings = ws.require_initialised()
    ws.require_segments()
    # Every batch may pick any level (a random mixed first batch, then BAMS): a budget below
    # the cheapest run was refused only by batch 2's select, after batch 1 was simulated.
    for flag, value in (("--budget", budget), ("--first-budget", first_budget)):
        if value is not None:
            check_buys_a_run(value, settings.costs, flag)
    if screen is not None:  # refused now, not after the discovery batches
        if not then_estimate:
            raise OptionValueError(f"--screen {screen} screens the estimate: pass --then-estimate")
        if isinstance(screen, str) and screen not in ("auto", "off"):
            raise OptionValueError(f"--screen {screen}: a share of K in (0, 1), auto, or off")
        if not isinstance(screen, str):
            check_share(screen, settings)
    elif then_estimate:
        screen = defaults.SCREEN
    opts = Options(
        simulator=simulator,
        batches=batches,
        budget=budget,
        first_budget=budget if first_budget is None else first_budget,
        then_estimate=then_estimate,
        samples=samples,
        screen=screen,
        results_dir=Path(results_dir) if results_dir else ws.root / "loop-results",
        abandon_failed=abandon_failed,
        retries=retries,
        clusters=clusters,
        workers=workers,
        wait=wait,
    )
    # Now, not after its pending lists.
    _refuse_discovery_inside_a_screen(ws, _discovery_batches(ws), batches)
    total = batches + (1 if then_estimate else 0)
    steps: list[dict[str, Any]] = []
    ingested: set[Path] = set()
    selected: set[int] = set()  # batches drawn by this run
    with (
        workspace_lock(
            ws.root,
            wait=wait,
            lock_file=LOOP_LOCK_FILE,
            refusal="another `bams-cli loop` runs here:",
        ),
        _stopped_by_signals(),
    ):
        # Under the loop's lock: a second loop refused by it probes nothing, and the folder
        # made and removed by the probe cannot be one another loop has just made.
        _check_results_dir(ws, opts.results_dir)
        current: tuple[str, str | None, int | None] | None = None  # the step under way
        try:
            while True:
                current = None
                step = _next_step(ws, opts, frozenset(selected))
                if step is None:
                    break
                current = name, kind, number = step
                if name == "ingest-results":
                    # Ingested once and still pending: say so, without a second "ingest"
                    # progress line for a step that is not run again.
                    assert kind is not None and number is not None
                    if (results := _results_file(opts, kind, number)) in ingested:
                        if (t := _retries_spent(results) + 1) > opts.retries:
                            _stuck(ws, opts, kind, number, results)
                        kept = _set_aside(results, f"retried-{t}")
                        ingested.discard(results)
                        if on_warning is not None:
                            pend = ws.pending()
                            left = pend.filter(pend[kind] == number).height
                            on_warning(
                                f"{_describe(name, kind, number)}: {left} request"
                                f"{'s' if left != 1 else ''} still without a result: "
                                f"simulating {'them' if left != 1 else 'it'} again (retry "
                                f"{t} of {opts.retries}; the results are kept as {kept})"
                            )
                        continue
                if on_step is not None:
                    on_step(_describe(name, kind, number), _progress(ws, opts), total)
                steps.append(_run(ws, opts, name, kind, number, ingested, on_warning))
                if name == "select" and number is not None:
                    selected.add(number)
        except LoopStopped as exc:
            raise LoopStopped(exc.signum, _stopped(ws, exc.signum, current)) from None
    if on_step is not None:
        on_step("done", total, total)
    latest = latest_estimate(ws)
    return {
        "workspace": str(ws.root),
        "batches": len(_discovery_batches(ws)),  # as --batches counts them
        "plans": len(pipeline.plan_numbers(ws)),
        "steps": steps,
        "unchanged": not steps,
        "results_dir": str(opts.results_dir),
        "estimate_file": None if latest is None else latest["file"],
        "estimate": latest,
    }


def _check_results_dir(ws: Workspace, folder: Path) -> None:
    """Refuse a --results-dir that is the workspace or one of its own folders (its results
    files, ``batch-0001.csv``, would take the names of the hand-off lists there, and the
    loop would ingest a hand-off list as results and set it aside), a file, a link to
    nowhere, or a folder that cannot be made or written."""
    where = folder.resolve()
    own = [ws.root, ws.batches_dir, ws.estimates_dir, ws.history_dir, ws.report_dir]
    if any(where == p.resolve() for p in own):
        raise OptionValueError(
            f"--results-dir {folder}: is the workspace's own folder; give the results a "
            f"folder of their own (the default is {ws.root / 'loop-results'})"
        )
    if where.exists() and not where.is_dir():
        raise OptionValueError(f"--results-dir {folder}: is a file, not a folder")
    # Checked on the path as given, as the simulator's step will use it (a link resolves
    # to a folder that may not be there): made, or written, then left as it was, so a
    # folder the loop cannot use is refused before any step and a refused loop leaves
    # nothing behind.
    if folder.is_symlink() and not folder.exists():
        raise OptionValueError(
            f"--results-dir {folder}: a link to {os.readlink(folder)}, which does not exist"
        )
    made = [p for p in (folder, *folder.parents) if not p.exists()]
    probe = folder / f".bams-loop-probe-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.touch()
    except OSError as exc:
        doing = "made" if made else "written"
        raise OptionValueError(
            f"--results-dir {folder}: cannot be {doing} ({exc.strerror or exc})"
        ) from None
    finally:
        with contextlib.suppress(OSError):
            probe.unlink(missing_ok=True)
        for p in made:
            with contextlib.suppress(OSError):
                p.rmdir()


@contextmanager
def _stopped_by_signals() -> Iterator[None]:
    """Raise ``LoopStopped`` where the loop stands on any of ``STOP_SIGNALS``, once: a
    second signal while the first unwinds (ending the simulator) changes nothing. A signal
    ignored when the loop started stays ignored: ``nohup bams-cli loop ...`` outlives its
    terminal. The loop becomes its descendants' subreaper (Linux), so that a simulator's
    children whose shell died first (Ctrl-C reaches the whole group at once) stay its
    descendants, for ``_end_tree`` to find."""
    if threading.current_thread() is threading.main_thread():
        _become_subreaper()
    with stopping.raising(STOP_SIGNALS, LoopStopped, take=stopping.not_ignored):
        yield


PR_SET_CHILD_SUBREAPER = 36  # <linux/prctl.h>


def _become_subreaper() -> None:
    """Orphaned descendants of this process are re-parented to it, not to init (Linux;
    elsewhere nothing)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)


def _stopped(ws: Workspace, signum: int, step: tuple[str, str | None, int | None] | None) -> str:
    """The one line a stopped loop ends with: what it was doing, and how to resume."""
    name = signal.Signals(signum).name
    again = "run the same `bams-cli loop` again to resume"
    if step is not None and step[0] == "simulate":
        listed = f"{step[1]} {step[2]}"
        return (
            f"stopped by {name} while the simulator ran on {listed}: the simulator and every "
            f"process it started were ended, and {listed} still awaits results; {again}"
        )
    where = f" during `{_describe(*step)}`" if step is not None else ""
    return (
        f"stopped by {name}{where}; {ws.root} is as the last finished step left it (writes "
        f"are atomic): {again}"
    )


def _describe(name: str, kind: str | None, number: int | None) -> str:
    return name if kind is None else f"{kind} {number}: {name}"


def _progress(ws: Workspace, opts: Options) -> int:
    """Lists finished: batches without pending picks (and the estimate, once written)."""
    pend = ws.pending()
    waiting = set(pend["batch"].drop_nulls().to_list())
    done = sum(1 for b in _discovery_batches(ws)[: opts.batches] if b not in waiting)
    if opts.then_estimate and any(ws.estimates_dir.glob("estimate-*.json")):
        done += 1
    return done


def _discovery_batches(ws: Workspace) -> list[int]:
    """The study's discovery batches, which ``--batches`` counts: every batch but a
    screen's (``estimate --plan --screen``), whose cheap runs belong to the estimate."""
    out = []
    for n in ws.batch_numbers():
        options = read_metadata_json(schemas.batch_path(ws.root, n)).get("options")
        if not (isinstance(options, dict) and options.get("strategy") == "screen"):
            out.append(n)
    return out


def _refuse_discovery_inside_a_screen(ws: Workspace, discovery: list[int], batches: int) -> None:
    """Raise ``LoopError`` if ``--batches`` asks for discovery batches while a screen
    awaits its confirmation (``estimate --plan --screen``, auto by default): their level-0
    picks would land among the segments the screen counted as unknown, and the
    confirmation would refuse them (its design no longer holds), losing the screen's cheap
    runs. ``discovery``: the study's discovery batches (``_discovery_batches``)."""
    if len(discovery) >= batches:
        return
    screen = open_screen(ws)
    if screen is not None:
        raise LoopError(
            f"{screen} awaits its level-0 confirmation, and a new discovery batch would put "
            "level-0 results inside it; finish the estimate first (`bams-cli loop` with "
            f"--batches {len(discovery)} --then-estimate), then run this loop for more batches"
        )


def _results_file(opts: Options, kind: str, number: int) -> Path:
    return opts.results_dir / f"{kind}-{number:04d}.csv"


def _model_fresh(ws: Workspace) -> bool:
    try:
        ws.require_fresh_model()
    except WorkspaceError:
        return False
    return True


def _next_step(
    ws: Workspace, opts: Options, selected: frozenset[int] = frozenset()
) -> tuple[str, str | None, int | None] | None:
    """(step, list kind, list number) the study needs next, or None when the loop is done.
    ``selected``: the batches this loop run drew."""
    pend = ws.pending()
    if pend.height:
        for kind in ("batch", "plan"):
            numbers = sorted(set(pend[kind].drop_nulls().to_list()))
            if numbers:
                n = int(numbers[0])
                if _results_file(opts, kind, n).exists():
                    return ("ingest-results", kind, n)
                return ("simulate", kind, n)
    numbers = ws.batch_numbers()
    if numbers and ws.read_observations().height == 0:
        # Every request so far abandoned: nothing to fit, a new random batch (``_run``),
        # whatever --batches says: batches that brought no result do not count against it.
        # But not after one this run drew: a simulator that fails every run (abandoned by
        # --abandon-failed) had the loop draw batch after batch for ever.
        if numbers[-1] in selected:
            last = handoff_path(ws.root, "batch", numbers[-1])
            raise LoopError(
                f"every request of batch {numbers[-1]} failed and was abandoned, and the study "
                f"has no result yet: check the simulator on {last}, then run the same "
                "`bams-cli loop` again (it draws a new random batch)"
            )
        return ("select", "batch", numbers[-1] + 1)
    discovery = _discovery_batches(ws)
    if len(discovery) < opts.batches:
        _refuse_discovery_inside_a_screen(ws, discovery, opts.batches)
        if not numbers:
            return ("select", "batch", 1)
        if not _model_fresh(ws):
            return ("fit", None, None)
        return ("select", "batch", numbers[-1] + 1)
    plans = pipeline.plan_numbers(ws)
    if opts.then_estimate:
        if not plans:
            if not _model_fresh(ws):
                return ("fit", None, None)
            return ("estimate --plan", "plan", 1)
        from bams_cli import stages  # the numerical stack loads only when a plan exists

        info = stages.plan_info(ws, plans[-1])
        if info.stage < info.stages:
            # A staged estimate: the next stage is drawn from the model refitted on this
            # one's results (``core.design``).
            if not _model_fresh(ws):
                return ("fit", None, None)
            return ("estimate --plan", "plan", plans[-1] + 1)
        if not (ws.estimates_dir / f"estimate-{plans[-1]:04d}.json").exists():
            return ("estimate", "plan", plans[-1])
        if ws.estimate_out_of_date(plans[-1]):  # a result it read was replaced since
            return ("estimate", "plan", plans[-1])
    if not _model_fresh(ws) and ws.read_observations().height:
        # Last, the model of every result (after --batches 1 too: the next `select`,
        # `report` and `status` read it).
        return ("fit", None, None)
    return None


def _run(
    ws: Workspace,
    opts: Options,
    name: str,
    kind: str | None,
    number: int | None,
    ingested: set[Path],
    on_warning: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    root, wait = ws.root, opts.wait
    record: dict[str, Any] = {"step": name, "list": None if kind is None else f"{kind} {number}"}
    out: dict[str, Any] = {}
    if name == "fit":
        out = pipeline.fit(root, wait=wait)
        record["up_to_date"] = bool(out.get("up_to_date", False))
    elif name == "select":
        assert number is not None
        # A random batch while there is no model: the first, or one after a first batch
        # whose every request was abandoned (``_next_step``).
        first = not ws.model_path.exists()
        out = pipeline.select(
            root,
            strategy="random" if first else "bams",
            mixed_fidelity=first,
            budget=opts.first_budget if first else opts.budget,
            clusters=opts.clusters,
            workers=opts.workers,
            batch=number,
            wait=wait,
        )
        record["picks"] = out["picks"]
    elif name == "simulate":
        assert kind is not None and number is not None
        try:
            record["results"] = str(_simulate(ws, opts, kind, number))
        except SimulatorFailed as exc:
            # A simulator that fails now and then (a licence server, a busy cluster): with
            # retries left the run is a try of its own, noted on disk, and the list is
            # simulated again.
            results = _results_file(opts, kind, number)
            if (t := _retries_spent(results) + 1) > opts.retries:
                raise SimulatorFailed(exc.what, exc.returncode, opts.retries) from None
            note = results.with_name(f"retried-{t}-{results.stem}{FAILED_RUN_SUFFIX}")
            with transaction() as tx:
                tx.write_text(note, f"{exc.what}\n")
            if on_warning is not None:
                on_warning(
                    f"{_describe(name, kind, number)}: the simulator exited with "
                    f"{exc.returncode} (noted in {note}); simulating the list again, retry "
                    f"{t} of {opts.retries}"
                )
            record["failed"] = exc.returncode
    elif name == "ingest-results":
        assert kind is not None and number is not None
        results = _results_file(opts, kind, number)
        _check_written_for(results, handoff_path(root, "batch" if kind == "batch" else "plan",
                                                 number))  # fmt: skip
        ingested.add(results)  # ingested again only after a retry (``loop``)
        try:
            # With retries left, what failed is simulated again rather than abandoned.
            if opts.abandon_failed and _retries_spent(results) >= opts.retries:
                out = abandon.ingest_results_abandoning_failed(root, results, wait=wait)
                record["abandoned"] = n = out["abandoned"]["abandoned"]
                if n and on_warning is not None:
                    on_warning(
                        f"{_describe(name, kind, number)}: {n} failed request"
                        f"{'s' if n != 1 else ''} abandoned (--abandon-failed): "
                        + (
                            "the estimate bounds what they might have been"
                            if kind == "plan"
                            else "not asked for again"
                        )
                    )
            else:
                out = pipeline.ingest_results(root, results, wait=wait)
        except InputError as exc:
            if Path(exc.file) != results:  # a damaged workspace file, not the simulator's
                raise
            if (t := _retries_spent(results) + 1) > opts.retries:
                raise LoopError(_rejected(results, exc, kind, number)) from None
            # A try of its own: set aside, and the list is simulated again.
            kept = _set_aside(results, f"retried-{t}")
            ingested.discard(results)
            if on_warning is not None:
                on_warning(
                    f"{_describe(name, kind, number)}: {exc} (kept as {kept}; simulating "
                    f"the list again, retry {t} of {opts.retries})"
                )
            record["rejected"] = str(kept)
            return record
        record["ingested"] = out["ingested"]
    elif name == "estimate --plan":
        # --screen draws the screen once; with the screen drawn, the same step confirms it.
        drawn = opts.screen is not None and screen_path(Workspace(root), number or 1).exists()
        screen = None if drawn else opts.screen
        out = pipeline.estimate_plan(root, samples=opts.samples, screen=screen, wait=wait)
        record["to_simulate"] = out["cheap_runs"] if "screen_file" in out else out["to_simulate"]
    elif name == "estimate":
        # An estimate computed again (a result it read was replaced since) keeps the
        # --failed-as bounds it was computed with.
        bounds = opts.abandon_failed
        if number is not None and Workspace(root).estimate_path(number).exists():
            earlier = Workspace(root).read_estimate(number).get("abandoned") or {}
            bounds = bounds or earlier.get("failed_as") == "bounds"
        out = pipeline.estimate_compute(
            root, plan_number=number, failed_as="bounds" if bounds else None, wait=wait,
        )  # fmt: skip
        record["estimate_file"] = out["estimate_file"]
    if on_warning is not None:
        # A no-op re-run repeats nothing it warned of when the work was done, save what
        # it says of the settings as they are now (``fit``'s ``settings_warnings``).
        said = out.get("settings_warnings" if out.get("up_to_date") else "warnings")
        for text in said or []:
            on_warning(f"{_describe(name, kind, number)}: {text}")
    return record


def _simulate(ws: Workspace, opts: Options, kind: str, number: int) -> Path:
    """Run the user's simulator on a hand-off list; its results land under their final
    name only when it exits 0."""
    which: Kind = "batch" if kind == "batch" else "plan"
    handoff = handoff_path(ws.root, which, number)
    results = _results_file(opts, kind, number)
    results.parent.mkdir(parents=True, exist_ok=True)
    running = results.with_name(f".simulator-{results.name}.json")
    # Before the pending-only list is written again: an earlier simulator may be reading it.
    _refuse_an_earlier_loops_simulator(running, kind, number)
    handoff = _still_pending(ws, which, number, handoff, results.parent)
    done = _run_simulator(opts, kind, number, handoff, results, running)
    if handoff != handoff_path(ws.root, which, number):
        # The pending-only list is made afresh for each run of the simulator: one kept
        # goes stale as results come in, and reads as work still to do. (After a failed
        # run it stays, named in the error, to run the command again by hand.)
        handoff.unlink(missing_ok=True)
    return done


def fill_simulator(template: str, handoff: Path, results: Path) -> str:
    """The simulator command: ``{handoff}`` and ``{results}`` replaced by the paths, quoted
    for the shell; a placeholder the user quoted already (``'{handoff}'``,
    ``"{results}"``, e.g. inside ``python -c '...'``) gets the bare path."""
    for name, path in (("handoff", handoff), ("results", results)):
        for q in ("'", '"'):
            template = template.replace(f"{q}{{{name}}}{q}", f"{q}{path}{q}")
        template = template.replace(f"{{{name}}}", shlex.quote(str(path)))
    return template


def _run_simulator(
    opts: Options, kind: str, number: int, handoff: Path, results: Path, running: Path
) -> Path:
    partial = results.with_name(f".partial-{results.name}")
    partial.unlink(missing_ok=True)
    command = fill_simulator(opts.simulator, handoff, partial)
    import psutil

    before = {p.pid for p in psutil.Process().children()}  # not the simulator's
    # Noted before it starts: a loop killed between the start and a note of the pid left
    # a simulator no later loop could know of.
    token = uuid.uuid4().hex
    _record_simulator(running, token, command)
    env = {**os.environ, SIMULATOR_TOKEN_ENV: token}
    try:
        proc = subprocess.Popen(command, shell=True, stdout=subprocess.DEVNULL, env=env)
    except BaseException:
        running.unlink(missing_ok=True)
        raise
    try:
        with memory.outside(proc.pid):  # the simulator's memory is not the loop's
            returncode = proc.wait()
    except BaseException:
        _end_tree(proc, before)
        partial.unlink(missing_ok=True)
        running.unlink(missing_ok=True)
        raise
    running.unlink(missing_ok=True)
    if returncode != 0:
        partial.unlink(missing_ok=True)  # what a failed run wrote is never results
        raise SimulatorFailed(
            f"--simulator: `{command}` exited with {returncode} on {handoff}", returncode
        )
    if not partial.exists():
        raise LoopError(
            f"--simulator: `{command}` exited 0 but wrote no {partial}; the command must "
            "write the results file named by {results}"
        )
    os.replace(partial, results)
    return results


def _still_pending(ws: Workspace, kind: Kind, number: int, handoff: Path, folder: Path) -> Path:
    """The hand-off list to simulate: ``handoff`` itself, or, when some of its requests
    have results already (a run that crashed, whose results file was deleted to run the
    simulator again), a list of the others in ``folder`` (``state.pending``, whose list
    beside the hand-off list ``ingest-results`` keeps as well). Simulated again, the
    requests with results would come back with other values from a simulator with
    run-to-run noise, and ingesting them would be refused as conflicts."""
    rows = pending.pending_rows(ws, kind, number)
    if rows is None:
        return handoff
    subset = folder / pending_path(handoff).name
    with transaction() as tx:
        tx.write_text(subset, rows.write_csv())
    return subset


#: Set in the simulator's environment to the token noted in ``.simulator-NAME.json``.
SIMULATOR_TOKEN_ENV = "BAMS_CLI_SIMULATOR_RUN"


def _record_simulator(record: Path, token: str, command: str) -> None:
    """Note the simulator about to run beside its results file, for a loop started after
    this one was killed by SIGKILL (which leaves the simulator running) to find: every
    process whose environment holds ``token``."""
    with transaction() as tx:
        tx.write_text(record, json.dumps({"token": token, "command": command}))


def _simulator_processes(token: str) -> list[int]:
    """The pids of the running processes whose environment holds ``token`` (a simulator
    and every process it started that kept its environment)."""
    import psutil

    found = []
    for p in psutil.process_iter():
        with contextlib.suppress(psutil.Error):  # gone, or another user's
            if p.environ().get(SIMULATOR_TOKEN_ENV) == token and p.status() != psutil.STATUS_ZOMBIE:
                found.append(p.pid)
    return sorted(found)


def _refuse_an_earlier_loops_simulator(record: Path, kind: str, number: int) -> None:
    """Refuse to simulate a list again while the simulator an earlier, killed loop started
    on it still runs: both would write the same results file. A record none of whose
    processes runs any more is removed."""
    try:
        doc = json.loads(record.read_text())
        token, command = str(doc["token"]), str(doc["command"])
    except FileNotFoundError:
        return
    except (OSError, ValueError, KeyError, TypeError):
        record.unlink(missing_ok=True)  # unreadable: written by a loop killed mid-write
        return
    pids = _simulator_processes(token)
    if not pids:
        record.unlink(missing_ok=True)
        return
    raise LoopError(
        f"{kind} {number}: the simulator an earlier `bams-cli loop` started on it is still "
        f"running (`{command}`, pid {', '.join(map(str, pids))}); that loop was killed "
        f"without ending it. End it (`kill {' '.join(map(str, pids))}`) or let it finish, "
        "then run the same `bams-cli loop` again (it simulates the list again)"
    )


def _end_tree(proc: subprocess.Popen[bytes], before: set[int] | None = None) -> None:
    """End the simulator and every process it started: SIGTERM to each, and SIGKILL for
    what is left after ``SIMULATOR_GRACE_S``. The tree is listed before anything is
    signalled: a shell's children, once it is gone, are no longer its descendants."""
    import psutil

    try:
        root = psutil.Process(proc.pid)
        tree = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        tree = []
    # Orphans of a shell that died first are this process's own children now (the loop is
    # their subreaper): every child that was not there before the simulator started
    # (``before``: e.g. multiprocessing's resource tracker).
    with contextlib.suppress(psutil.NoSuchProcess):
        known = {p.pid for p in tree} | (before or set())
        for child in psutil.Process().children():
            if child.pid not in known:
                with contextlib.suppress(psutil.NoSuchProcess):
                    tree += [child, *child.children(recursive=True)]
    for p in tree:
        with contextlib.suppress(psutil.NoSuchProcess):
            p.terminate()
    _, alive = psutil.wait_procs(tree, timeout=SIMULATOR_GRACE_S)
    for p in alive:
        with contextlib.suppress(psutil.NoSuchProcess):
            p.kill()
    proc.wait()


#: A simulator run that exited non-zero and was retried is noted as
#: ``retried-K-STEM`` + this, beside the results files.
FAILED_RUN_SUFFIX = ".failed.txt"


def _retries_spent(results: Path) -> int:
    """Retries already spent on ``results``' list: the tries kept beside it as
    ``retried-K-NAME`` before each retry (its results ingested with some requests still
    without one, or refused by ``ingest-results``) and the simulator runs that exited
    non-zero (``retried-K-STEM.failed.txt``); on disk, so a loop stopped and run again
    counts them too. A file refused when no try is left (``rejected-NAME``) does not
    count: no retry followed it."""
    folder = results.parent
    return sum(1 for _ in folder.glob(f"retried-*-{results.name}")) + sum(
        1 for _ in folder.glob(f"retried-*-{results.stem}{FAILED_RUN_SUFFIX}")
    )


#: How much older than its hand-off list a results file may be and still be ingested.
MTIME_SLACK_S = 10.0


def _check_written_for(results: Path, handoff: Path) -> None:
    """Refuse a results file older than the hand-off list it would answer: it was not
    written for that list (a results folder kept from an earlier study, or shared with
    another), and from the same seed it would be ingested as this study's results; it is
    left where it is."""
    try:
        # By more than MTIME_SLACK_S: a results folder on a file system with coarser
        # timestamps (1-2 s) or on a server whose clock lags a little is not refused.
        older = results.stat().st_mtime < handoff.stat().st_mtime - MTIME_SLACK_S
    except FileNotFoundError:
        return
    if older:
        raise LoopError(
            f"{results}: older than the hand-off list it would answer ({handoff}), so not "
            "written for it (a --results-dir kept from an earlier study, or shared with "
            "another?); move it away to have the loop simulate the list, or `touch` it to "
            "ingest it as it is, then run the same `bams-cli loop` again"
        )


def _set_aside(results: Path, prefix: str) -> Path:
    """Rename ``results`` to ``PREFIX-NAME`` beside it (``PREFIX-K-NAME`` if that is taken):
    kept, out of the loop's way."""
    target = results.with_name(f"{prefix}-{results.name}")
    k = 1
    while target.exists():
        k += 1
        target = results.with_name(f"{prefix}-{k}-{results.name}")
    os.replace(results, target)
    return target


def _rejected(results: Path, exc: InputError, kind: str, number: int) -> str:
    """Move a results file ``ingest-results`` refused out of the loop's way, and say so.

    Left in place, the next loop would ingest it again and fail the same way, whatever was
    fixed in the simulator. It is kept (as ``rejected-<name>``, numbered if one is there
    already) for the user to read, and the next loop simulates the list again."""
    target = _set_aside(results, "rejected")
    return (
        f"{exc} (the simulator's results for {kind} {number}: moved to {target}; fix the "
        "simulator and run the same `bams-cli loop` again, which simulates the list again)"
    )


def _stuck(ws: Workspace, opts: Options, kind: str, number: int, results: Path) -> None:
    pend = ws.pending()
    left = pend.filter(pend[kind] == number)
    flag = f"--{kind} {number}"
    raise LoopError(
        f"{results}: ingested, but {left.height} requests of {kind} {number} still have no "
        f"result (failed runs, or rows missing); rerun them and ingest the results, record "
        f"them as lost with `bams-cli abandon -w {shlex.quote(str(ws.root))} {flag}`"
        + (
            " (--abandon-failed abandons rows with a failed status, not rows missing from the file)"
            if opts.abandon_failed
            else " (or run the loop with --abandon-failed)"
        )
        + ", or move the file aside (its results are in the workspace) to run the "
        "simulator again on those requests alone (--retries N does that N times by itself)"
    )
