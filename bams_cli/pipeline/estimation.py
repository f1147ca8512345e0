"""``bams-cli estimate``: the plan (``--plan``) and the failure-rate estimate from its results."""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import defaults
from bams_cli import stages as stages_mod
from bams_cli.errors import (
    OptionError,
    OptionValueError,
    PendingResultsError,
    StaleStateError,
    WorkspaceError,
)
from bams_cli.pipeline import screening
from bams_cli.pipeline._common import (
    SID,
    Progress,
    check_samples,
    finite_or_none,
    ids_in,
    locked,
    plan_numbers,
    read_scores,
)
from bams_cli.pipeline._handoff import (
    PLAN_INTERNAL,
    cheap_failures,
    describe_leads,
    lead_evidence,
    observed_level0,
    passthrough_columns,
    write_handoff,
)
from bams_cli.pipeline.fitting import load_posterior, model_transform
from bams_cli.settings import Settings
from bams_cli.state import handoff as contract
from bams_cli.state import pending, schemas
from bams_cli.state.io import (
    read_metadata_json,
    read_state,
    transaction,
)
from bams_cli.state.workspace import Workspace, stale_log

if TYPE_CHECKING:
    from bams_cli.core.estimate import RateEstimates

#: Where a plan's seed came from (its metadata's ``seed_source``).
SEED_OPTION = "--seed"
SEED_INHERITED = "stage 1's --seed"  # or, for a screened estimate's plan, the screen's


@locked
def estimate_plan(
    root: Path,
    *,
    samples: float | None = None,
    alpha: float = defaults.ALPHA,
    defensive: float = defaults.DEFENSIVE,
    design: str = "poisson",
    weighting: str = "auto",
    stages: int = defaults.STAGES,
    stage1_share: float = defaults.STAGE1_SHARE,
    new_series: bool = False,
    seed: int | None = None,
    screen: float | str | None = defaults.SCREEN,
    handoff_internal: bool = False,
    allow_pending: bool = False,
) -> dict[str, Any]:
    """Plan one stage of the rate-estimation sample: inclusion probabilities and the hand-off.

    The estimate runs in ``stages`` stages (``core.design``, ``stages``): the first plan of
    a series fixes the total budget K (``samples``) and the stages' weights, and spends
    ``stage1_share`` of K; each later call, once the previous stage's results are in and
    the model refitted on them, draws the next stage with its share. Every stage's design
    comes from the model checked against the level-0 outcomes of every finished plan
    (``weighting="auto"``): the candidate with the smallest predicted variance among
    uniform, the calibrated design and the paper's p^alpha form. ``weighting`` "uniform"
    or "p-alpha" (with ``alpha``, ``defensive``) forces one; designs "fixed" and
    "with-replacement" are single-stage p^alpha plans, as the paper's.

    While an earlier plan awaits results this refuses (exit code 3, so a Makefile re-run
    does not draw a second plan); ``allow_pending`` draws another anyway.

    The draw is seeded by the study seed and the plan's number (so re-running a study
    reproduces its plans), or by ``seed`` alone when given: the same seed then gives the
    same plan from the same scores, and another seed a fresh one, without editing the
    settings. The seed and the random stream are recorded in the plan's metadata.

    This is ``bams-cli estimate --plan``; ``estimate_compute`` is ``bams-cli estimate``.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    samples : float, optional
        The simulation budget K of a new estimate (default: 5 x the GP's p x N).
    alpha : float, default ``defaults.ALPHA``
        The p^alpha design's exponent.
    defensive : float, default ``defaults.DEFENSIVE``
        Uniform share eps mixed into the sampling distribution.
    design : {"poisson", "fixed", "with-replacement"}, default "poisson"
        Horvitz-Thompson with Poisson sampling, systematic fixed-size, or the paper's
        sampling with replacement.
    weighting : {"auto", "uniform", "p-alpha"}, default "auto"
        How the inclusion probabilities are chosen (above).
    stages : int, default ``defaults.STAGES``
        For a new estimate: how many stages K is spent in (1 to 10).
    stage1_share : float, default ``defaults.STAGE1_SHARE``
        Share of K that stage 1 spends, in (0, 1).
    new_series : bool, default False
        Start a new estimate although the last one has stages to go.
    seed : int, optional
        Draw a fresh plan from this seed (above).
    screen : float, "auto", "off" or None, default ``defaults.SCREEN`` ("auto")
        Start a screened estimate: spend this share of K on cheap-level runs of a Poisson
        sample first (``bams_cli.pipeline.screening``); the next call, once their results
        are in and the model refitted, draws the level-0 confirmation. The summary is then
        the screen's (``screen_file``, ``batch``, ``handoff`` ...), not a plan's. "auto"
        screens ``defaults.SCREEN_HINT_SHARE`` of a new estimate's K wherever the study
        has a cheap level and the refit can condition on the screen
        (``screening.auto_share``), and otherwise plans as without it (it confirms an open screen and
        continues a staged estimate as a plain call does), saying which in a note; it
        plans without a screen where none can be drawn (a design other than poisson, or
        level-0 runs awaiting results beside --allow-pending). "off" or None: no screen.
    handoff_internal : bool, default False
        Also put the internal columns in the CSV hand-off.
    allow_pending : bool, default False
        Draw a plan although an earlier plan or a discovery batch awaits results.
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``plan`` (its number), ``plan_file``, ``handoff``
        (the CSV to simulate), ``results_template``, ``design``, ``samples_K``, ``stage``
        and ``stages``, ``weighting``, ``to_simulate``, ``known_stratum``,
        ``gp_rate_estimate``, ``seed``, ``notes``.

    Raises
    ------
    PendingResultsError
        An earlier plan awaits results (exit code 3; ``allow_pending`` draws anyway).
    OptionValueError
        An option out of range or unknown; exit code 2.
    WorkspaceError
        No workspace or no fitted model.
    StaleStateError
        The model is older than the observation log.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    st = stages_mod  # the series and the evidence of finished plans
    from bams_cli.core import design as dz
    from bams_cli.core.estimate import (
        DESIGNS,
        gp_estimate,
        inclusion_probabilities,
        max_failure_weight,
        model_weight,
        plan_sample,
    )

    if design not in DESIGNS:
        raise OptionValueError(f"--design {design!r}: choose one of {', '.join(DESIGNS)}")
    if weighting not in WEIGHTINGS:
        raise OptionValueError(f"--weighting {weighting!r}: choose one of {', '.join(WEIGHTINGS)}")
    check_samples(samples)
    if not 0 <= alpha < np.inf:
        raise OptionValueError(f"--alpha {alpha:g}: must be a finite number >= 0")
    if not 0 <= defensive <= 1:
        raise OptionValueError(f"--defensive {defensive:g}: must lie in [0, 1]")
    if not 1 <= stages <= 10:
        raise OptionValueError(f"--stages {stages}: must be between 1 and 10")
    if not 0 < stage1_share < 1:
        raise OptionValueError(f"--stage1-share {stage1_share:g}: must lie in (0, 1), e.g. 0.5")
    if seed is not None and seed < 0:
        raise OptionValueError(f"--seed {seed}: must be an integer >= 0")
    ws = Workspace(root)
    settings = ws.require_initialised()
    pend = ws.pending()
    # A second plan while the first awaits results would be drawn from the same scores
    # and double-count the rate's sample; a plan beside a pending batch (select refuses the
    # same) would come from a model that has not seen its results, and a pending pick that
    # fails would not count as known. Make re-running a target must do neither.
    kind: contract.Kind
    for kind, then in (
        ("plan", "run `bams-cli estimate`, or pass --allow-pending to draw another plan beside it"),
        ("batch", "refit before planning the estimate, or pass --allow-pending to plan "
         "without them"),
    ):  # fmt: skip
        waiting = sorted(set(pend[kind].drop_nulls().to_list())) if pend.height else []
        if waiting and not allow_pending:
            many = len(waiting) > 1
            names = {"plan": ("estimate plan", "estimate plans"), "batch": ("batch", "batches")}
            name = names[kind][many]
            lists = " and ".join(str(pending.to_simulate(ws, kind, int(n))) for n in waiting)
            picks = int(pend[kind].is_in(waiting).sum())
            raise PendingResultsError(
                f"{ws.root}: {name} "
                f"{', '.join(str(n) for n in waiting)} await{'' if many else 's'} results "
                f"for {picks} {'pick' if picks == 1 else 'picks'}; simulate {lists}, "
                f"ingest the results and {then}"
            )
    model = ws.require_fresh_model()
    ids, _, _, p_all = read_scores(ws, len(settings.gammas))
    # The largest gamma's p_n bounds every other gamma's (f <= g_small implies f <= g_large),
    # so one sample planned on it serves every configured gamma.
    g_plan = int(np.argmax(settings.gammas))
    p = p_all[:, g_plan]
    known = observed_level0(ws, ids)
    n = len(ids)
    gp_rate, _ = gp_estimate(p)
    n_unknown = int((~known).sum())
    number = (plan_numbers(ws) or [0])[-1] + 1

    warnings: list[str] = []
    new_estimate = None  # the note that this plan starts a new estimate beside an earlier one
    census = None  # the note that K takes every unknown segment, so one stage
    leads = np.zeros(len(ids), dtype=bool)  # sampled with certainty (stage 1 only)
    lead_facts: dict[str, Any] | None = None  # open_leads' evidence, where it was asked
    series_leads = 0
    # Which stage is this? The next stage of an unfinished series, or stage 1 of a new one.
    staged = design == "poisson"
    prev = st.plan_info(ws, number - 1) if number > 1 else None
    # A stage is drawn from the model checked on the previous stage's outcomes, so a plan
    # drawn beside a pending one (--allow-pending) starts a new estimate instead.
    continuing = (
        staged
        and not new_series
        and prev is not None
        and prev.stage < prev.stages
        and st.plan_complete(ws, prev.number)
    )
    if (
        prev is not None
        and not continuing
        and prev.stage >= prev.stages
        and not ws.estimate_path(prev.number).exists()
        and st.plan_complete(ws, prev.number)
    ):
        # The earlier estimate's results are all in and nobody computed it: a new plan
        # does not replace it, and the user may have meant `estimate`, not `--plan`.
        lost = ws.abandoned_open("plan", prev.number).height
        bounds = " --failed-as bounds" if lost else ""
        warnings.append(
            f"plan {prev.number} has all its results"
            + (f" (or abandoned: {lost})" if lost else "")
            + " but its estimate was never computed: `bams-cli estimate -w "
            f"{shlex.quote(str(ws.root))} --plan-number {prev.number}{bounds}` computes it; "
            f"this plan, {number}, starts a new estimate beside it"
        )
    # A screen drawn for this plan number and not dropped (--new-series) is confirmed
    # first, whatever series came before it; --screen starts a new estimate.
    open_screen = screening.screen_path(ws, number).exists() and not new_series
    auto_note = None
    # A level-0 result arriving between a screen and its confirmation would move a segment
    # of U into the known stratum after pi1 was drawn for it.
    level0_pending = pend.filter(pl.col("fidelity") == 0).height if pend.height else 0
    if screen == "auto":
        if open_screen or continuing or settings.n_levels == 1 or n_unknown == 0:
            share = None
        elif design != "poisson":
            share = None
            auto_note = (
                "--screen auto: no screen (a screen confirms with a Poisson design, not "
                f"--design {design})"
            )
        elif level0_pending:
            share = None
            auto_note = (
                "--screen auto: no screen (level-0 runs await results, and a screen's U "
                "must not change before its confirmation)"
            )
        else:
            K_auto, _ = _plan_samples(
                ws, settings, samples, g_plan=g_plan, gp_rate=gp_rate, n=n,
                n_unknown=n_unknown, design="poisson",
            )  # fmt: skip
            share, auto_note = screening.auto_share(
                model, settings, K=K_auto, n_unknown=n_unknown,
                n_observations=ws.read_observations().height,
            )  # fmt: skip
    elif screen == "off" or screen is None:
        share = None
    elif isinstance(screen, str):
        raise OptionValueError(f"--screen {screen!r}: a share of K in (0, 1) such as 0.3, or auto")
    else:
        share = screen
    if share is not None and open_screen:
        # Drawing it again would spend K twice, and a screen drawn on the first one's
        # cheap results re-weights the segments those picked: --new-series says so.
        raise WorkspaceError(
            f"--screen: {screening.screen_path(ws, number)} awaits its confirmation; run "
            f"`bams-cli estimate -w {ws.root} --plan` (no --screen) once its results are in "
            "and fitted, or pass --new-series to drop it and draw a new screen"
        )
    if open_screen:
        return _confirm_screen(
            ws, settings, number=number, ids=ids, p_all=p_all, g_plan=g_plan, known=known,
            samples=samples, seed=seed, model=model, gp_rate=gp_rate,
            handoff_internal=handoff_internal,
        )  # fmt: skip
    if share is not None and not continuing:
        # A new screen (a stale one of this number, dropped by --new-series, is overwritten).
        if design != "poisson":
            raise OptionValueError(
                f"--screen: a screen confirms with a Poisson design, not --design {design}"
            )
        screening.check_share(share, settings)
        if level0_pending:
            raise PendingResultsError(
                f"--screen: {level0_pending} level-0 runs await results; ingest them (or "
                f"abandon them) first: the screen's U is every segment without a level-0 "
                "result, and must not change before the screen is confirmed"
            )
        samples, warned = _plan_samples(
            ws, settings, samples, g_plan=g_plan, gp_rate=gp_rate, n=n,
            n_unknown=n_unknown, design="poisson",
        )  # fmt: skip
        # Its own stream: the confirmation, plan `number`, draws from the plan's. A screen
        # drawn again (--new-series) after the first one's results must not reuse its
        # uniforms: S1' = {u < pi1'} with pi1' fitted on S1 = {u < pi1}'s cheap runs would
        # re-weight the segments S1 picked. The log's size and the batch count tell them apart.
        state = [ws.read_observations().height, len(ws.batch_numbers())]
        stream, seed_source = (
            ([int(seed), 30_000, *state], SEED_OPTION)
            if seed is not None
            else ([settings.seed, 30_000 + number, *state], "study settings")
        )
        evidence, _ = st.mix_evidence(ws, settings.gammas[g_plan])
        from bams_cli.core.screen import lead_budget

        # The open cheap-level leads are in the screen with certainty (``core.screen``).
        leads, lead_facts = open_leads(
            ws, ids, p, known, settings.gammas[g_plan], pend,
            K=lead_budget(samples, share),
            scales=model["hyperparameters"].get("scales") or (),
        )  # fmt: skip
        # Only leads with a result at the screen's level: they cost the screen nothing (a
        # lead seen at another cheap level alone stays with the design).
        obs1 = ws.read_observations().filter(pl.col("fidelity") == screening.SCREEN_LEVEL)
        at = np.flatnonzero(leads)
        leads[at[~ids_in(ids[at], obs1[SID].to_numpy())]] = False
        out = screening.draw_screen(
            ws, settings, number=number, ids=ids, p=p, known=known, K=samples,
            share=share, leads=leads, lead_facts=lead_facts,
            posterior=dz.risk_posterior(evidence, prior=screening.risk_prior(model, settings)),
            confirm_prior=screening.confirm_prior(model, settings),
            rng=np.random.default_rng(stream),
            meta={"seed": stream[0], "seed_source": seed_source, "rng_stream": stream,
                  "plan_gamma": settings.gammas[g_plan],
                  "model_hash": model["observations_hash"]},
            handoff_internal=handoff_internal,
        )  # fmt: skip
        return out | {
            "notes": [n for n in [auto_note] if n] + out["notes"],
            "warnings": warnings + warned,
        }
    if share is not None:
        assert prev is not None
        raise WorkspaceError(
            f"--screen: plan {prev.number} is stage {prev.stage} of {prev.stages} of an "
            "estimate; plan its next stage (drop --screen), or pass --new-series to start a "
            "screened estimate instead"
        )
    if continuing:
        assert prev is not None
        if samples is not None and not math.isclose(samples, prev.series_K, rel_tol=1e-9):
            raise WorkspaceError(
                f"--samples: plan {prev.number} is stage {prev.stage} of {prev.stages} of an "
                f"estimate with K = {prev.series_K:g} fixed at its stage 1; this plan is its "
                "next stage and spends its share of K (drop --samples, or pass the same K); pass "
                "--new-series to start a new estimate instead"
            )
        series, stage, n_stages = prev.series, prev.stage + 1, prev.stages
        series_K, shares, weights = prev.series_K, prev.shares, prev.weights
        # Stage 1's certain leads came out of K; the stages share what was left.
        series_leads = int(prev.meta.get("series_leads") or 0)
        K_stage = (series_K - series_leads) * shares[stage - 1]
    else:
        if prev is not None:
            # Said, since the report and status then show this newest estimate: a trial
            # re-ran `estimate --plan` on a finished study and its headline moved to the
            # new, smaller sample without a word.
            earlier = [k.number for k in st.series_plans(ws, prev.number)]
            new_estimate = (
                f"plan {number} starts a new estimate; the earlier one (plan"
                f"{'s' if len(earlier) > 1 else ''} {', '.join(map(str, earlier))}) stays in "
                "its files, and the report and status show this one once its results are in"
            )
        samples, warned = _plan_samples(
            ws, settings, samples, g_plan=g_plan, gp_rate=gp_rate, n=n, n_unknown=n_unknown,
            design=design,
        )  # fmt: skip
        warnings += warned
        # K that takes every unknown segment is a census: one stage, exact. Split, stage 2
        # would be a census only in expectation (of what stage 1 happened to leave).
        n_stages = stages if staged and 2 * stages <= samples < n_unknown else 1
        if staged and stages > 1 and samples >= n_unknown > 0:
            census = (
                f"K = {samples:g} takes every segment without a level-0 result: one stage, "
                "a census (the estimate is exact once its results are in)"
            )
        series, stage, series_K = number, 1, float(samples)
        rest = (1.0 - stage1_share) / (n_stages - 1) if n_stages > 1 else 0.0
        shares = [stage1_share, *([rest] * (n_stages - 1))] if n_stages > 1 else [1.0]
        # The open cheap-level leads are sampled with certainty (``open_leads``): they come
        # out of K, and the stages share the rest over the segments that are not leads.
        if staged and weighting == "auto" and series_K < n_unknown:
            leads, lead_facts = open_leads(
                ws, ids, p, known, settings.gammas[g_plan], pend,
                K=series_K,
                scales=model["hyperparameters"].get("scales") or (),
            )  # fmt: skip
        series_leads = int(leads.sum())
        weights = dz.stage_weights(shares, series_K - series_leads, n_unknown - series_leads)
        K_stage = (series_K - series_leads) * shares[0]
    K_stage = min(K_stage, float(n_unknown - int(leads.sum())))
    # A later stage of a series whose stage 1 was drawn with --seed draws from that seed
    # too (its own stream per stage): fresh plans of one study, each from its own --seed,
    # had shared stage 2's draws, all from the study's seed.
    inherited = None
    if continuing and seed is None and prev is not None:
        if prev.meta.get("seed_source") in (SEED_OPTION, SEED_INHERITED):
            inherited = int(prev.meta["seed"])
    if seed is not None:
        stream, seed_source = [int(seed), 10_000], SEED_OPTION
    elif inherited is not None:
        # 20,000 + stage: never a stream a plan of the study's own seed draws from
        # ([seed, 10,000 + plan number]), whatever seed the series was given.
        stream, seed_source = [inherited, 20_000 + stage], SEED_INHERITED
    else:
        stream, seed_source = [settings.seed, 10_000 + number], "study settings"
    rng = np.random.default_rng(stream)
    unknown = np.flatnonzero(~known)
    pu = p[unknown]
    certain_u = leads[unknown]
    n_certain = int(certain_u.sum())
    # What the design and the evidence of this plan stand on: U without the certain leads,
    # whose selection is not p_n's (their p_n would tell where failures fall only in part).
    pr = pu[~certain_u]
    # What the finished plans say about trusting p_n (lam: the share of failure mass it
    # does not explain); the prior alone before any plan has results.
    evidence, evidence_plans = st.mix_evidence(ws, settings.gammas[g_plan])
    # A later stage keeps its series' prior; a new series takes the current model's.
    recorded = (prev.meta.get("model_check") or {}).get("prior") if continuing and prev else None
    post = dz.risk_posterior(evidence, prior=screening.risk_prior(model, settings, recorded))
    choice = None
    if staged:
        with np.errstate(divide="ignore"):
            if unknown.size == 0:  # every level-0 value is known: a census, nothing to draw
                pi_u = np.zeros(0)
            elif weighting == "auto":
                choice = dz.choose_design(
                    pr, K=K_stage, posterior=post, alpha=alpha, defensive=defensive
                )
                pi_u = np.ones(unknown.size)
                pi_u[~certain_u] = choice.pi
            elif weighting == "uniform":
                pi_u = np.full(unknown.size, K_stage / max(unknown.size, 1))
            else:
                pi_u = inclusion_probabilities(pu, alpha=alpha, defensive=defensive, K=K_stage)
        from bams_cli.core.estimate import SamplePlan, draw_poisson

        sampled = draw_poisson(pi_u, rng)
        K_drawn = K_stage + n_certain
        plan = SamplePlan(
            "poisson", n, unknown.astype(np.int64), pi_u / max(K_drawn, 1e-300), pi_u,
            K_drawn, sampled, np.ones(sampled.size, np.int64),
        )  # fmt: skip
        # The interval's allowance for a failure no stage has seen, per gamma: where the
        # least-trusted calibrated model the evidence allows puts failures.
        w_model = [
            dz.unseen_failure_weight(
                post.allowance_risk(p_all[unknown[~certain_u], g]), pi_u[~certain_u]
            )
            for g in range(len(settings.gammas))
        ]
    else:
        with np.errstate(divide="ignore"):
            plan = plan_sample(
                p, K=K_stage, rng=rng, known=known, alpha=alpha, defensive=defensive,
                design=design,  # type: ignore[arg-type]
            )  # fmt: skip
        prob_u = plan.q if design == "with-replacement" else plan.pi
        w_model = [
            model_weight(p_all[plan.unknown, g], prob_u, design=design, K=plan.budget)  # type: ignore[arg-type]
            for g in range(len(settings.gammas))
        ]
    # What the known stratum saved: the inclusion probability its segments would have had.
    saved = 0.0
    if known.any() and design != "with-replacement":
        full = inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=min(K_stage, n))
        saved = float(full[known].sum())
    sampled_idx = plan.sampled_pool_index
    known_idx = np.flatnonzero(known)
    predicted = (
        {k: round(v, 6) for k, v in choice.predicted.items()} if choice is not None else None
    )
    weighting_used = (
        choice.name if choice is not None else ("p^alpha" if weighting != "uniform" else "uniform")
    )
    stage_info = {
        "series": series,
        "stage": stage,
        "stages": n_stages,
        "series_K": series_K,
        "stage_shares": shares,
        "stage_weights": weights,
        "series_leads": series_leads,
    }
    check = {**post.summary(), "plans": evidence_plans}
    meta = {
        "plan": number,
        "design": design,
        "samples": K_stage + n_certain,
        "leads_certain": n_certain,
        "lead_ids": ids[unknown[certain_u]].astype(str).tolist(),
        "lead_evidence": lead_facts,
        "alpha": alpha,
        "defensive": defensive,
        "weighting": weighting_used,
        "weighting_option": weighting,
        "predicted_vs_uniform": predicted,
        "model_check": check,
        **stage_info,
        "n_pool": n,
        "n_unknown": n_unknown,
        "p_mean_unknown": float(pr.mean()) if pr.size else None,
        "risk_norms": dz.risk_norms(dz.relative_risk(pr)).tolist(),
        "risk_taus": list(dz.TAUS),
        **_plan_meta_tail(
            settings,
            g_plan,
            p_all,
            model,
            max_failure_weight(plan),
            w_model,
            stream,
            seed_source,
        ),
    }
    path, handoff_path, template = write_plan(
        ws, settings, number, ids, p, sampled_idx=sampled_idx, known_idx=known_idx,
        pi=plan.pi[plan.sampled], draws=plan.counts, q=plan.q[plan.sampled], meta=meta,
        handoff_internal=handoff_internal,
    )  # fmt: skip
    # A new estimate where a screen measured better: said, not done (it is not the default).
    hint = screening.screen_hint(model, ws.root) if stage == 1 and settings.n_levels > 1 else None
    lead_note = describe_leads(meta["leads_certain"], lead_facts, settings.gammas[g_plan])
    notes = [
        n for n in [new_estimate, census, lead_note, design_note(meta), auto_note or hint] if n
    ]
    return {
        "plan": number,
        "plan_file": str(path),
        "handoff": str(handoff_path),
        "results_template": str(template),
        "design": design,
        "samples_K": meta["samples"],
        **stage_info,
        "leads_certain": meta["leads_certain"],
        "weighting": weighting_used,
        "predicted_vs_uniform": predicted,
        "model_check": check,
        "to_simulate": len(sampled_idx),
        "simulations_certain": int((plan.pi[plan.sampled] >= 1.0).sum()),
        "known_stratum": int(len(known_idx)),
        "simulations_saved_by_known_stratum": round(saved, 3),
        "gp_rate_estimate": gp_rate,
        "plan_gamma": settings.gammas[g_plan],
        "alpha": alpha,
        "defensive": defensive,
        "seed": stream[0],
        "seed_source": meta["seed_source"],
        "notes": notes,
        "warnings": warnings,
    }


def open_leads(
    ws: Workspace,
    ids: np.ndarray,
    p: np.ndarray,
    known: np.ndarray,
    gamma: float,
    pend: pl.DataFrame,
    *,
    K: float,
    scales: Sequence[float] = (),
) -> tuple[np.ndarray, dict[str, Any]]:
    """The segments a new staged estimate samples with certainty: the open leads.

    A lead is a segment whose result at a cheap level is at or below ``gamma`` (a failure
    the cheap simulator saw) with no level-0 result, none awaited and none abandoned (its
    simulation failed for good: certainty would ask for it again). Only levels in level
    0's units count (``cheap_failures``). A failure seen only
    at the cheap level is a lead, not a finding, and leads fail at level 0 far more often
    than their p_n says (the model shrinks one cheap run towards its smooth surroundings):
    on the fresh problems 40-100% of them did where p_n put many at 0.01 or below. The
    estimate confirms each: pi = 1 adds no variance, it takes the lead's share of K from
    the rest, and the failures it confirms are in hand. At most ``core.design.lead_share``
    of K, the highest p_n first: half, unless the leads the study has already run at level
    0 show them failing less often than ``defaults.LEAD_HIT_MIN`` (then a tenth).

    Returns
    -------
    leads : ndarray of bool over the pool
    facts : dict
        ``open`` (leads before the cap), ``pairs`` and ``failed`` (the evidence:
        ``_handoff.lead_evidence``) and ``share`` (the cap's share of K).
    """
    cheap = cheap_failures(ws, ids, gamma, scales)
    lead = cheap & ~known
    if pend.height:
        lead &= ~ids_in(ids, pend.filter(pl.col("fidelity") == 0)[SID].to_numpy())
    gone = ws.read_abandoned()
    if gone.height:
        lead &= ~ids_in(ids, gone.filter(pl.col("fidelity") == 0)[SID].to_numpy())
    from bams_cli.core.design import certain_leads, lead_share

    pairs, failed = lead_evidence(ws, ids, cheap, gamma)
    share = lead_share(pairs, failed)
    facts = {"open": int(lead.sum()), "pairs": pairs, "failed": failed, "share": share}
    return certain_leads(p, known, lead, K, share), facts


def _plan_samples(
    ws: Workspace,
    settings: Settings,
    samples: float | None,
    *,
    g_plan: int,
    gp_rate: float,
    n: int,
    n_unknown: int,
    design: str,
) -> tuple[float, list[str]]:
    """K of a new estimate: ``samples``, or the default (below), and the warning when no
    level-0 failure has checked the model's rate that the default rests on."""
    warnings: list[str] = []
    unchecked = None  # the default K's 5 p N when no level-0 failure has checked p
    defaulted = samples is None
    if samples is None:
        # The paper's K = 5 p N with the GP's own p; a GP that explains failures away
        # can put p N near 0, so the failures already seen at level 0 set a floor, and
        # so does defaults.PLAN_MIN_SAMPLES: a GP that has seen no failure at level 0
        # can put its rate at 1e-6 and K at 5, an estimate of "0, at most 0.5".
        obs0 = ws.read_observations().filter(pl.col("fidelity") == 0)
        seen = int((obs0["value"] <= settings.gammas[g_plan]).sum())
        paper = 5 * max(gp_rate * n, seen + 1)
        samples = float(round(max(paper, defaults.PLAN_MIN_SAMPLES)))
        unchecked = paper if seen == 0 else None
    if design == "with-replacement":
        samples = float(round(samples))
    if design != "with-replacement":
        samples = min(samples, float(n_unknown))
    if unchecked is not None:
        if unchecked >= defaults.PLAN_MIN_SAMPLES:
            why = f"K = {samples:g} rests on that rate"
        elif samples == defaults.PLAN_MIN_SAMPLES:
            why = (
                f"K = {samples:g} is the default's floor (the paper's 5 p N gives {unchecked:.3g})"
            )
        else:
            why = f"K = {samples:g}, every segment without a level-0 result"
        # The interval is two-sided: with no failure among K uniform samples its upper
        # limit is the 1 - (1 - confidence)/2 quantile, -ln(0.05)/K = 3.0/K at 90%.
        warnings.append(
            "no level-0 failure is known, so nothing has checked the model's rate "
            f"({gp_rate:.2g}); {why}: pass --samples K sized for the smallest rate "
            "the estimate must rule out (with no failure among K uniform samples the "
            "90% interval's upper limit is about 3.0/K)"
        )
    elif defaulted and n_unknown > 0 and samples >= defaults.PLAN_LARGE_SHARE * n_unknown:
        # Said, since a trial study with a 6% rate and a model that put it at 19% was
        # handed K = 9,265 of 9,991 segments without a word: nearly a census.
        warnings.append(
            f"the default K = {samples:g} (5 x the model's rate {gp_rate:.2g} x N) is "
            f"{samples / n_unknown:.0%} of the {n_unknown:,} segments without a level-0 "
            "result; pass --samples K to spend less (the estimate stays unbiased at any K)"
        )
    return float(samples), warnings


def write_plan(
    ws: Workspace,
    settings: Settings,
    number: int,
    ids: np.ndarray,
    p: np.ndarray,
    *,
    sampled_idx: np.ndarray,
    known_idx: np.ndarray,
    pi: np.ndarray,
    draws: np.ndarray,
    q: np.ndarray,
    meta: dict[str, Any],
    handoff_internal: bool,
) -> tuple[Path, Path, Path]:
    """Write plan ``number`` (its Parquet file and CSV hand-off) in one transaction.

    ``sampled_idx``, ``known_idx``: pool indices of the sampled segments (with their
    ``pi``, ``draws`` and ``q``) and of the known stratum; ``p``: p_n over the pool.
    Returns the plan's path, its hand-off's and the results template's.
    """
    # The sampled rows are the plan's requests (level 0, in hand-off order); the known
    # stratum's rows follow with the contract's columns null: nothing to simulate there.
    requests = contract.contract_columns(
        "plan",
        number,
        ids[sampled_idx],
        np.zeros(len(sampled_idx), np.int64),
        settings,
        ["estimate"] * len(sampled_idx),
    )
    n_known = len(known_idx)
    cols: dict[str, Any] = {
        name: pa.concat_arrays([arr, pa.nulls(n_known, arr.type)])
        for name, arr in requests.items()
        if name != SID
    }
    cols = {
        SID: pa.array(np.concatenate([ids[sampled_idx], ids[known_idx]]).astype(str), pa.string()),
        "stratum": ["sampled"] * len(sampled_idx) + ["known"] * n_known,
        "pi": np.concatenate([pi, np.ones(n_known)]),
        "draws": np.concatenate([draws, np.zeros(n_known, np.int64)]),
        "q": np.concatenate([q, np.zeros(n_known)]),
        "p_n": np.concatenate([p[sampled_idx], p[known_idx]]),
        **cols,
    }
    cols |= passthrough_columns(ws, np.concatenate([sampled_idx, known_idx]), taken=cols)
    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    handoff_path = ws.estimates_dir / f"plan-{number:04d}-handoff.csv"
    state = schemas.PLAN.conform(pa.table(cols), meta)
    with transaction() as tx:
        tx.write_parquet(path, state)
        _, template = write_handoff(
            tx, state.slice(0, len(sampled_idx)), handoff_path, PLAN_INTERNAL, handoff_internal
        )
    return path, handoff_path, template


def _plan_meta_tail(
    settings: Settings,
    g_plan: int,
    p_all: np.ndarray,
    model: dict[str, Any],
    w_max: float,
    w_model: Sequence[float],
    stream: list[int],
    seed_source: str,
) -> dict[str, Any]:
    """What every plan's metadata records beside its design: the interval's weights, the
    gamma and model it was drawn for, the GP's own estimate then, and its random stream."""
    from bams_cli.core.estimate import gp_estimate

    return {
        # Undefined weights (no segment with pi < 1; p_n = 0 over U) are null, never a
        # bare NaN/Infinity in the metadata's JSON; reading them back gives NaN again.
        "w_max": finite_or_none(w_max),
        "w_model": [finite_or_none(w) for w in w_model],
        "plan_gamma": settings.gammas[g_plan],
        "model_hash": model["observations_hash"],
        # The GP's own estimate (mean p_n, variance bound) per gamma, as of this plan:
        # `estimate` reports it when the plan's results have not been fitted yet.
        "gp_at_plan": [list(gp_estimate(p_all[:, g])) for g in range(len(settings.gammas))],
        "seed": stream[0],
        "seed_source": seed_source,
        "rng_stream": stream,
    }


def _confirm_screen(
    ws: Workspace,
    settings: Settings,
    *,
    number: int,
    ids: np.ndarray,
    p_all: np.ndarray,
    g_plan: int,
    known: np.ndarray,
    samples: float | None,
    seed: int | None,
    model: dict[str, Any],
    gp_rate: float,
    handoff_internal: bool,
) -> dict[str, Any]:
    """Plan ``number``: the level-0 confirmation of the screen of the same number
    (``screening.confirm_screen``), a one-stage plan at pi = pi1 pi2."""
    from bams_cli.core import design as dz

    smeta = read_metadata_json(screening.screen_path(ws, number))
    if seed is not None:
        stream, seed_source = [int(seed), 10_000], SEED_OPTION
    elif smeta.get("seed_source") == SEED_OPTION:  # the screen's --seed: its own stream
        stream, seed_source = [int(smeta["seed"]), 40_000], SEED_INHERITED
    else:
        stream, seed_source = [settings.seed, 10_000 + number], "study settings"
    evidence, evidence_plans = stages_mod.mix_evidence(ws, settings.gammas[g_plan])
    # The screen's priors, whatever the refit on its cheap runs says of the cheap level.
    post = dz.risk_posterior(
        evidence, prior=screening.risk_prior(model, settings, smeta.get("risk_prior"))
    )
    post_confirm = dz.risk_posterior(
        evidence, prior=screening.recorded_confirm_prior(model, settings, smeta)
    )
    c = screening.confirm_screen(
        ws, settings, number=number, ids=ids, p_all=p_all, g_plan=g_plan, known_now=known,
        samples=samples, posterior=post, confirm_posterior=post_confirm,
        rng=np.random.default_rng(stream),
    )  # fmt: skip
    p = p_all[:, g_plan]
    K2 = float(c["K2"])
    # The confirmed design against uniform sampling of K, as the checked model predicts.
    predicted = None if c["predicted_vs_uniform"] is None else {"screen": c["predicted_vs_uniform"]}
    sampled_idx, pi = c["sampled_idx"], c["pi"]
    check = {**post.summary(), "plans": evidence_plans}
    stage_info = {
        "series": number, "stage": 1, "stages": 1, "series_K": K2, "stage_shares": [1.0],
        "stage_weights": [1.0],
    }  # fmt: skip
    meta = {
        "plan": number,
        "design": "poisson",
        "samples": K2,
        "alpha": defaults.ALPHA,
        "defensive": defaults.DEFENSIVE,
        "weighting": "screen",
        "weighting_option": "screen",
        "predicted_vs_uniform": predicted,
        "model_check": check,
        **stage_info,
        "n_pool": len(ids),
        "n_unknown": c["n_unknown"],
        # No p_mean_unknown: the confirmation is drawn on cheap-run evidence p_n lacks, so
        # its outcomes would not say how far p_n alone is to be trusted (stages.mix_evidence).
        **_plan_meta_tail(
            settings, g_plan, p_all, model, c["w_max"], c["w_model"], stream, seed_source
        ),
        "screen": c["screen"],
    }
    path, handoff_path, template = write_plan(
        ws, settings, number, ids, p, sampled_idx=sampled_idx, known_idx=c["known_idx"],
        pi=pi, draws=np.ones(len(sampled_idx), np.int64), q=pi / max(K2, 1e-300), meta=meta,
        handoff_internal=handoff_internal,
    )  # fmt: skip
    scr = c["screen"]
    return {
        "plan": number,
        "plan_file": str(path),
        "handoff": str(handoff_path),
        "results_template": str(template),
        "design": "poisson",
        "samples_K": K2,
        **stage_info,
        "weighting": "screen",
        "predicted_vs_uniform": predicted,
        "model_check": check,
        "to_simulate": len(sampled_idx),
        "simulations_certain": int((pi >= 1.0).sum()),
        "known_stratum": len(c["known_idx"]),
        "simulations_saved_by_known_stratum": 0.0,
        "gp_rate_estimate": gp_rate,
        "plan_gamma": settings.gammas[g_plan],
        "alpha": defaults.ALPHA,
        "defensive": defaults.DEFENSIVE,
        "seed": stream[0],
        "seed_source": seed_source,
        "screen": scr,
        "notes": [
            n
            for n in [
                f"plan {number} confirms the screen of {scr['screened']} segments "
                f"({scr['file']}) at level 0 with {K2:g} of K = {scr['series_K']:g}; each "
                "sampled segment is weighted by 1 / (pi1 pi2)",
                design_note(meta),
            ]
            if n
        ],
        "warnings": [],
    }


def design_note(meta: dict[str, Any]) -> str | None:
    """One line when a plan's design was predicted to do no better than uniform sampling."""
    predicted = meta.get("predicted_vs_uniform") or {}
    chosen = predicted.get(meta.get("weighting"))
    if chosen is None or chosen <= UNIFORM_NOTE_RATIO:
        return None
    what = (
        "the screened design no better than uniform sampling of K"
        if meta.get("weighting") == "screen"
        else "no design much better than uniform sampling"
    )
    return (
        f"plan {meta['plan']}: the checked model predicted {what} ({meta['weighting']}, "
        f"{chosen:.2f}x uniform's variance); the estimate rests on the sample, not the model"
    )


#: ``estimate --plan --weighting``: "auto" picks the design with the smallest predicted
#: variance under the checked model; the others force one.
WEIGHTINGS = ("auto", "uniform", "p-alpha")

#: A chosen design predicted to reach at most this fraction of uniform's variance saving
#: gets a note: the model does not help the estimate.
UNIFORM_NOTE_RATIO = 0.9


@dataclasses.dataclass(frozen=True)
class _PlanSample:
    """One plan's sample with its level-0 outcomes, ready for the estimator."""

    sampled_ids: np.ndarray
    fails: np.ndarray
    lost: list[str]
    estimate_with: Callable[[np.ndarray], Any]


def _plan_sample(
    ws: Workspace,
    number: int,
    gammas: np.ndarray,
    confidence: float,
    failed_as: str | None,
    interval: str = "gamma",
) -> _PlanSample:
    """Plan ``number``'s sample, outcomes and estimator (``estimate_with(fails)``).

    Abandoned planned segments are refused, or kept for the bounds (``bams_cli.abandon``).
    """
    from bams_cli import abandon
    from bams_cli.core.estimate import estimate_from_sample

    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    meta = read_metadata_json(path)
    plan = pl.from_arrow(schemas.PLAN.check(read_state(path), path))
    assert isinstance(plan, pl.DataFrame)
    obs = ws.read_observations().filter(pl.col("fidelity") == 0).select(SID, "value")
    joined = plan.join(obs, on=SID, how="left")
    lost = abandon.planned_abandoned(ws, number, path, joined, failed_as)
    missing = joined.filter(pl.col("value").is_null() & ~pl.col(SID).is_in(lost))
    if missing.height:
        names = ", ".join(missing[SID].head(3).to_list())
        raise PendingResultsError(
            f"{path}: {missing.height} planned segments have no level-0 result ({names}"
            f"{', ...' if missing.height > 3 else ''}); simulate "
            f"{pending.to_simulate(ws, 'plan', number)} and ingest the results"
        )
    sampled = joined.filter(pl.col("stratum") == "sampled")
    known = joined.filter(pl.col("stratum") == "known")
    fails = sampled["value"].to_numpy()[:, None] <= gammas[None, :]
    known_fails = (known["value"].to_numpy()[:, None] <= gammas[None, :]).sum(axis=0)

    def estimate_with(fails: np.ndarray) -> Any:
        return estimate_from_sample(
            sampled["q" if meta["design"] == "with-replacement" else "pi"].to_numpy(),
            fails,
            design=meta["design"],
            n_pool=int(meta["n_pool"]),
            n_unknown=int(meta["n_unknown"]),
            budget=float(meta["samples"]),
            counts=sampled["draws"].to_numpy(),
            known_failures=known_fails,
            confidence=confidence,
            w_model=np.asarray(meta["w_model"], dtype=np.float64),  # null -> NaN: design weights
            interval=interval,  # type: ignore[arg-type]
            w_max=math.inf if meta.get("w_max") is None else float(meta["w_max"]),  # null: inf
        )

    return _PlanSample(sampled[SID].to_numpy(), fails, lost, estimate_with)


def plan_estimate(ws: Workspace, number: int, gammas: np.ndarray, confidence: float):  # noqa: ANN202
    """The HT estimate of one plan from its ingested level-0 results, per gamma."""
    sample = _plan_sample(ws, number, gammas, confidence, None)
    return sample.estimate_with(sample.fails)


@locked
def estimate_compute(
    root: Path,
    *,
    plan_number: int | None = None,
    confidence: float = 0.9,
    exact_variance: bool = False,
    failed_as: str | None = None,
    interval: str = "gamma",
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Compute the rate estimate from an ingested plan, for every configured gamma.

    A plan that is a later stage of a staged estimate is combined with its earlier stages
    (``core.design.combine_stages``); while stages remain, the estimate rests on the
    stages so far and says so. Planned segments abandoned for good (``bams-cli abandon``)
    are refused, unless ``failed_as="bounds"`` asks for the worst case over them
    (``bams_cli.abandon``).

    This is ``bams-cli estimate`` (without ``--plan``); it writes
    ``estimates/estimate-NNNN.json``, keeping an earlier, different estimate of the plan
    as ``estimate-NNNN.1.json`` (``.2`` ...).

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    plan_number : int, optional
        Which plan to compute (default: the latest).
    confidence : float, default 0.9
        Two-sided confidence level of the interval, in (0, 1).
    exact_variance : bool, default False
        Also compute the GP estimate's exact variance (pools of at most 50,000).
    failed_as : {"bounds"}, optional
        How to count planned segments that were abandoned (default: refuse).
    interval : {"gamma", "fay-feuer"}, default "gamma"
        The confidence interval: the gamma interval whose upper limit allows for one more
        failure of the model's weight, or Fay and Feuer's, which allows for the heaviest
        weight in U and so guarantees coverage (wider). "fay-feuer" is for one-stage plans.
    progress : callable ``(phase, done, total) -> None``, optional
        Called as the work advances (the CLI draws its progress bar with it).
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``plan``, ``design``, ``samples_K``, ``staging``,
        ``estimates`` (per gamma: ``gamma``, ``p_hat``, ``se``, ``ci_low``, ``ci_high``,
        ``rel_var``, ``distinct_failures_found``, ...), ``gp`` (the GP's own estimate per
        gamma), ``gp_model``, ``notes``, ``estimate_file``, ``earlier_estimate`` (null, or
        where this plan's earlier, different estimate was kept and its ``confidence`` and
        ``interval``: it is moved to ``estimate-NNNN.1.json``, ``.2`` ..., never lost).

    Raises
    ------
    PendingResultsError
        Planned segments have no level-0 result yet (exit code 3).
    AbandonedRunsError
        Planned segments were abandoned and ``failed_as`` is not given.
    OptionValueError
        A ``confidence`` outside (0, 1); exit code 2.
    WorkspaceError
        No workspace, or no such plan.
    StaleStateError
        ``exact_variance`` needs a model fitted on the current log.
    OptionError
        An unknown ``failed_as``.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    from bams_cli import abandon
    from bams_cli.core.design import combine_stages
    from bams_cli.core.estimate import gp_estimate

    if not 0 < confidence < 1:
        raise OptionValueError(f"--confidence {confidence:g}: must lie in (0, 1), e.g. 0.9")
    ws = Workspace(root)
    settings = ws.require_initialised()
    plans = plan_numbers(ws)
    if not plans:
        screen = screening.open_screen(ws)
        if screen is not None:
            # --screen (auto by default) drew a screen: no level-0 plan until confirmed.
            batch = read_metadata_json(screen).get("batch")
            pend = ws.pending()
            waiting = batch is not None and bool((pend["batch"] == batch).any())
            runs = f"simulate and ingest batch {batch} (its cheap runs), " if waiting else ""
            raise WorkspaceError(
                f"{ws.root}: no estimate yet: {screen.name} awaits its level-0 "
                f"confirmation; {runs}run `bams-cli fit -w {ws.root}`, then `bams-cli "
                f"estimate --plan -w {ws.root}` (`bams-cli status -w {ws.root}` names each "
                "step)"
            )
        ws.require_segments()  # a study without a pool is told the step it needs first
        raise WorkspaceError(
            f"{ws.root}: no estimate plan; run `bams-cli estimate --plan -w {ws.root}` first"
        )
    number = plans[-1] if plan_number is None else plan_number
    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    if not path.exists():
        raise WorkspaceError(f"{path}: no such plan (plans: {', '.join(map(str, plans))})")
    gammas = np.asarray(settings.gammas)
    # A staged estimate combines its series' stages up to this plan, with the weights
    # fixed at stage 1 (renormalised while later stages are still to come).
    series = stages_mod.series_plans(ws, number)
    if interval != "gamma" and len(series) > 1:  # combine_stages allows for the gamma's w only
        raise OptionError(
            f"--interval {interval}: plan {number} is stage {len(series)} of a staged "
            "estimate; it is for one-stage plans (estimate --plan --stages 1)"
        )
    samples = [_plan_sample(ws, k.number, gammas, confidence, failed_as, interval) for k in series]
    meta = series[-1].meta
    weights = np.asarray([series[-1].weights[k.stage - 1] for k in series], np.float64)
    if weights.sum() <= 0:
        # The stages done so far weigh nothing in the whole (a later one takes every
        # segment left, ``core.design.stage_weights``): until it is in, they are reported
        # by their shares of K.
        weights = np.asarray([series[-1].shares[k.stage - 1] for k in series], np.float64)
    weights /= weights.sum()
    splits = np.cumsum([len(x.sampled_ids) for x in samples])[:-1]
    fails = np.concatenate([x.fails for x in samples])
    lost = [i for x in samples for i in x.lost]

    def estimate_with(fails: np.ndarray) -> Any:
        parts = np.split(fails, splits)
        stage_est = [x.estimate_with(f) for x, f in zip(samples, parts, strict=True)]
        return combine_stages(stage_est, weights, n_pool=int(meta["n_pool"]))

    est = estimate_with(fails)
    remaining = series[-1].stages - series[-1].stage
    rows = []
    gp_rows = []
    # The IS estimate needs no model. Beside it goes the GP's own estimate: from the
    # current model when it has been fitted on the plan's results, else the model's as of
    # the plan (stored with it), so a large K never forces a refit just to get the number.
    model = ws.require_model(allow_newer_observations=True)
    at_plan = meta.get("gp_at_plan")
    if not model["fresh"] and (exact_variance or at_plan is None):
        why = "--exact-variance" if exact_variance else f"{path} (made by an older version)"
        fitted = int(sum(model.get("n_observations_per_level", [])))
        raise StaleStateError(
            f"{ws.model_path}: {stale_log(fitted, ws.read_observations().height)}, and {why} "
            f"needs a model of the current one; run `bams-cli fit -w {ws.root}` (or, faster, "
            f"`bams-cli fit -w {ws.root} --fixed-hyperparameters {ws.model_path}`: condition "
            "only, no training)"
        )
    if model["fresh"]:
        _, mu, sd, p_all = read_scores(ws, len(gammas))
        gp_values = [gp_estimate(p_all[:, g]) for g in range(len(gammas))]
    else:
        gp_values = [(float(m), float(b)) for m, b in at_plan or []]
    for g, gamma in enumerate(gammas):
        e = est[g]
        rows.append(
            {
                "gamma": float(gamma),
                "p_hat": e.p_hat,
                # Undefined numbers are null beside a note saying why, never NaN (issue 12):
                # the note says what se rests on when it is not the HT variance estimate.
                "se": finite_or_none(e.se),
                "variance_note": e.variance_note,
                "ci_low": e.ci_low,
                "ci_high": e.ci_high,
                "confidence": confidence,
                "rel_var": finite_or_none(e.rel_var),
                "rel_var_note": e.rel_var_note,
                "n_sampled": e.n_sampled,
                "failures_sampled": e.n_failures_sampled,
                "failures_known": e.n_known_failures,
                "distinct_failures_found": e.n_failures_found,
            }
        )
        if est.p_hat_unbiased is not None:
            # The Horvitz-Thompson sum (of a staged estimate, the stages' weighted sum),
            # which p_hat equals unless that fell below the failures found
            # (core.design.combine_stages) or above every segment not seen to pass.
            rows[-1]["p_hat_unbiased"] = float(est.p_hat_unbiased[g])
        gp_mean, gp_bound = gp_values[g]
        gp_row = {"gamma": float(gamma), "gp_p_hat": gp_mean, "gp_var_bound": gp_bound}
        if exact_variance:
            g_model = float(model_transform(ws, model).forward(float(gamma)))
            gp_row["gp_var_exact"] = _gp_exact_variance(ws, settings, mu, sd, g_model, progress)
        gp_rows.append(gp_row)
    staging = {
        "series": series[-1].series,
        "plans": [k.number for k in series],
        "stages_done": len(series),
        "stages": series[-1].stages,
        "weights": [round(float(w), 12) for w in weights],
        "series_K": series[-1].series_K,
        "note": (
            f"{remaining} more stage{'s' if remaining > 1 else ''} of this estimate "
            f"{'are' if remaining > 1 else 'is'} planned: refit on these results and run "
            f"`bams-cli estimate --plan -w {ws.root}`; until then the estimate rests on "
            f"{len(series)} of {series[-1].stages} stages"
            if remaining
            else None
        ),
    }
    summary: dict[str, Any] = {
        "plan": number,
        "design": meta["design"] if len(series) == 1 else "staged",
        "interval": interval,
        "samples_K": sum(float(k.meta["samples"]) for k in series),
        "staging": staging,
        "estimates": rows,
        "gp": gp_rows,
        "gp_model": "current" if model["fresh"] else "as of the plan",
        "notes": [],  # below: they speak of the estimate as reported
        # What it read from the log: a result replaced or abandoned since makes it out of
        # date (``status``, ``report``; ``Workspace.estimate_inputs_hash``).
        "inputs_hash": ws.estimate_inputs_hash(
            [k.number for k in series], [float(g) for g in gammas]
        ),
    }
    # Hook: with failed_as="bounds", the worst case over abandoned segments (bams_cli.abandon).
    worst = abandon.bound_estimates(
        summary, lost=lost, sampled_ids=np.concatenate([x.sampled_ids for x in samples]),
        fails=fails, estimate_with=estimate_with,
    )  # fmt: skip
    held = (
        held_notes(est, gammas)
        if worst is None
        else held_notes(worst, gammas, abandoned=summary["abandoned"]["count"])
    )
    summary["notes"] = [n for n in (design_note(k.meta) for k in series) if n] + held
    out = ws.estimate_path(number)
    text = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    earlier = _earlier_estimate(out, text)
    with transaction() as tx:
        if earlier is not None:  # another estimate of this plan: kept, never overwritten
            tx.write_text(Path(earlier["file"]), out.read_text())
        tx.write_text(out, text)
    summary["estimate_file"] = str(out)
    summary["earlier_estimate"] = earlier
    return summary


def held_notes(
    est: RateEstimates, gammas: Sequence[float] | np.ndarray, *, abandoned: int = 0
) -> list[str]:
    """A note per gamma whose p_hat is not the design-unbiased sum ``p_hat_unbiased``: a
    sum below the distinct failures found (stages' weighted sum: ``core.design.
    combine_stages``; a with-replacement sum), or above every segment not seen to pass,
    held there. ``abandoned``: ``est`` is ``--failed-as bounds``'s all-failing case over
    that many abandoned segments, and the notes say so (they count them as failures)."""
    if est.p_hat_unbiased is None:
        return []
    what = "the stages' weighted sum" if est.design == "staged" else "the estimator's sum"
    case = f", with the {abandoned} abandoned segments all failing" if abandoned else ""
    notes = []
    for g, gamma in enumerate(gammas):
        total, p_hat = float(est.p_hat_unbiased[g]), float(est.p_hat[g])
        if total > p_hat:
            notes.append(
                f"gamma {float(gamma):g}{case}: {what} ({total:.4g}) exceeded the share of "
                f"the pool not seen to pass, so p_hat is that share ({p_hat:.4g}): the rate "
                "is at most that; `p_hat_unbiased` keeps the sum, for pooling estimates "
                "across studies"
            )
        elif total < p_hat:
            notes.append(
                f"gamma {float(gamma):g}{case}: {what} ({total:.4g}) fell below the "
                f"{int(est.n_failures_found[g])} failures found, so p_hat is their share of "
                f"the pool ({p_hat:.4g}): the rate is at least that; `p_hat_unbiased` keeps "
                "the sum, for pooling estimates across studies"
            )
    return notes


def _earlier_estimate(out: Path, text: str) -> dict[str, Any] | None:
    """Where the plan's earlier estimate goes when ``text`` would replace a different one
    (another --confidence, --interval, model or log), and what it was: ``file``
    (``estimate-NNNN.1.json``, ``.2`` ...), ``confidence``, ``interval``. None when there
    is none, or it is the same."""
    if not out.exists() or out.read_text() == text:
        return None
    n = 1
    while (kept := out.with_name(f"{out.stem}.{n}{out.suffix}")).exists():
        n += 1
    try:
        doc = json.loads(out.read_text())
        confidence = doc["estimates"][0].get("confidence")
        interval = doc.get("interval", "gamma")
    except (ValueError, KeyError, IndexError, TypeError, AttributeError):
        confidence = interval = None  # damaged: kept as it is, described as nothing
    return {"file": str(kept), "confidence": confidence, "interval": interval}


def _gp_exact_variance(
    ws: Workspace,
    settings: Settings,
    mu: np.ndarray,
    sd: np.ndarray,
    gamma: float,
    progress: Progress | None,
) -> float:
    from bams_cli.core.estimate import gp_variance_exact

    ids, X = ws.read_pool()
    if len(ids) > 50_000:
        raise WorkspaceError(
            f"--exact-variance: the pool has {len(ids)} segments; the O(N^2) sum is limited to 50,000"
        )
    posterior, _ = load_posterior(ws, settings, ids, X)
    res = gp_variance_exact(
        mu,
        sd**2,
        lambda r, c: posterior.cov_theta0(X[r], X[c]),
        gamma,
        progress=(lambda done, total: progress("exact variance", done, total))
        if progress
        else None,
    )
    return float(res.var)
