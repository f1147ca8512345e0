"""``estimate --plan --screen SHARE``: a cheap-level screen, then level-0 confirmation in it.

A screened estimate takes two ``estimate --plan`` calls (``core.screen`` holds the math):

1. With ``--screen SHARE``: pi1 over U (the segments without a level-0 result) is the
   estimate's own design choice at the screen's size, SHARE x K spent at the cheap level's
   cost; a Poisson sample S1 is drawn and its cheap runs go out as a batch of the log
   (``batches/batch-NNNN``, strategy "screen"), so simulating, ingesting, abandoning and
   ``loop`` treat them as any batch. The screen itself, pi1 over the pool as it stood, is
   ``estimates/screen-NNNN.parquet``, named by the plan number its confirmation takes.
2. Once the batch's results are in and the model refitted on them, the next ``estimate
   --plan`` draws the confirmation: pi2 = 1 on the screen's lowest cheap results
   (``core.screen.screen_leads``) and the open leads, pi2 over the rest of S1 from the
   refitted p_n with what is left of K, and a plan (``plan-NNNN``) whose sampled segments carry pi = pi1 pi2. ``estimate``
   then computes it as any one-stage plan: T = sum y / (pi1 pi2) is unbiased whatever the
   refit did, since pi2 is fixed before any level-0 outcome of the confirmation is seen.

Segments of S1 whose cheap result is already in the log are not run again (the screen
observes them all the same) and cost nothing; neither are those whose cheap run was
abandoned: the refitted model's p_n stands in for their run.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import defaults
from bams_cli.errors import OptionValueError, PendingResultsError, WorkspaceError
from bams_cli.pipeline._common import SID, ids_in
from bams_cli.pipeline._handoff import (
    BATCH_INTERNAL,
    describe_leads,
    passthrough_columns,
    write_handoff,
)
from bams_cli.settings import Settings
from bams_cli.state import handoff as contract
from bams_cli.state import schemas
from bams_cli.state.io import read_metadata_json, read_state, transaction
from bams_cli.state.workspace import Workspace

#: The level a screen runs: the first cheap level (level 1).
SCREEN_LEVEL = 1


def screen_path(ws: Workspace, number: int) -> Path:
    """Where the screen confirmed by plan ``number`` lives."""
    return ws.root / schemas.SCREEN.relpath.format(n=number)


def open_screen(ws: Workspace) -> Path | None:
    """The screen awaiting its level-0 confirmation, if any: the next plan's."""
    from bams_cli.stages import plan_numbers

    plans = plan_numbers(ws)
    path = screen_path(ws, (plans[-1] if plans else 0) + 1)
    return path if path.exists() else None


def check_share(share: float, settings: Settings) -> float:
    """The cost of a screen's cheap run, once ``--screen SHARE`` is known to make sense."""
    if not 0 < share < 1:
        raise OptionValueError(
            f"--screen {share:g}: the share of K the screen spends must lie in (0, 1), e.g. 0.3"
        )
    if settings.n_levels < 2:
        raise OptionValueError(
            f"--screen {share:g}: the study has one fidelity level; a screen runs the cheap "
            "level (init --costs 1,0.1 declares one)"
        )
    cost = float(settings.costs[SCREEN_LEVEL])
    if not 0 < cost < 1:
        raise OptionValueError(
            f"--screen {share:g}: level {SCREEN_LEVEL}'s cost is {cost:g}; a screen needs a "
            "level cheaper than level 0 (cost in (0, 1))"
        )
    return cost


def cheap_level_discrepancy(model: dict[str, Any]) -> float | None:
    """The fitted model's level-1 discrepancy-plus-noise sd over its level-0 signal sd:
    how far the cheap level strays from level 0, as a share of level 0's own variation
    (scale-free). None for a one-level model or one without those hyperparameters."""
    hp = model.get("hyperparameters") or {}
    try:
        disc = float(hp["outputscales"][0]) + float(hp["noise"][SCREEN_LEVEL])
        signal = float(hp["outputscale0"])
    except (KeyError, IndexError, TypeError, ValueError):
        return None
    if not (signal > 0 and math.isfinite(disc) and disc >= 0):
        return None
    return math.sqrt(disc / signal)


def risk_prior(
    model: dict[str, Any], settings: Settings, recorded: Any = None
) -> tuple[float, float]:
    """The prior on lam an estimate step of this study is planned with: the one an earlier
    step of the same estimate ``recorded`` (a screen's ``risk_prior``, a stage's
    ``model_check.prior``), so an estimate keeps one prior from its first step to its last
    whatever later refits say of the cheap level; else, or where an older version recorded
    none, the model's (``core.design.risk_prior``: less trust in p_n where the fitted cheap
    level does not track level 0)."""
    from bams_cli.core.design import risk_prior as prior_for

    try:
        a, b = (float(v) for v in recorded)
        if a > 0 and b > 0 and math.isfinite(a + b):
            return (a, b)
    except (TypeError, ValueError):
        pass
    return prior_for(_study_discrepancy(model, settings))


def confirm_prior(model: dict[str, Any], settings: Settings) -> tuple[float, float]:
    """The prior on lam a screen drawn on this model records for its confirmation
    (``core.design.confirm_prior``: near-full trust in the refitted p_n where the fitted
    cheap level tracks level 0)."""
    from bams_cli.core.design import confirm_prior as prior_for

    return prior_for(_study_discrepancy(model, settings))


def recorded_confirm_prior(
    model: dict[str, Any], settings: Settings, screen_meta: dict[str, Any]
) -> tuple[float, float]:
    """The prior a screen's confirmation plans pi2 under: the one the screen recorded; a
    screen written before the confirmation had one of its own planned it as pi1."""
    return risk_prior(
        model, settings, screen_meta.get("confirm_prior", screen_meta.get("risk_prior"))
    )


def _study_discrepancy(model: dict[str, Any], settings: Settings) -> float | None:
    """``cheap_level_discrepancy`` of a study with a cheap level; None without one."""
    return cheap_level_discrepancy(model) if settings.n_levels > 1 else None


def screen_hint(model: dict[str, Any], root: Path) -> str | None:
    """A note for a new unscreened estimate when the cheap level tracks level 0 closely
    (``defaults.SCREEN_HINT_DISCREPANCY``)."""
    ratio = cheap_level_discrepancy(model)
    if ratio is None or ratio >= defaults.SCREEN_HINT_DISCREPANCY:
        return None
    return (
        f"the cheap level tracks level 0 closely (the model's discrepancy sd is {ratio:.2f} "
        "of its level-0 signal's): a screened estimate (`bams-cli estimate -w "
        f"{root} --plan --new-series --screen {defaults.SCREEN_HINT_SHARE:g}`, cheap runs "
        "of a sample first) had 0.31 to 1.06 times this design's variance on the suite's "
        f"problems below {defaults.SCREEN_HINT_DISCREPANCY:g}, and found more failures "
        "(docs/suite/screen_design.md)"
    )


def auto_share(
    model: dict[str, Any], settings: Settings, *, K: float, n_unknown: int, n_observations: int
) -> tuple[float | None, str]:
    """``--screen auto`` for a new estimate of budget ``K``: the share to screen (None: no
    screen) and a note saying why. It screens wherever the study has a cheap level and a
    refit can condition on every cheap run of the screen besides the log's
    ``n_observations`` (``refit_too_large``). Where the fitted cheap-level discrepancy is
    small (``screen_hint``'s rule) the refitted model ranks the screen well; elsewhere the
    screen's own lowest cheap results, which its confirmation takes with certainty
    (``core.screen.screen_leads``), are what the screen buys (docs/suite/screen_frontier.md).
    Where the cheap level is unrelated to level 0 those leads are a random share of the
    screen taken with certainty, and the design has about twice a uniform one's variance
    (docs/suite/unrelated_cheap.md); no evidence the study holds before the screen (its
    pairs, the fitted discrepancy) tells that level apart from a weak one that pays, so
    the note says so and ``--screen off`` is the user's."""
    from bams_cli.core.screen import screen_size

    limit = defaults.SCREEN_HINT_DISCREPANCY
    ratio = _study_discrepancy(model, settings)
    if ratio is None:
        return None, "--screen auto: no screen (the model has no cheap level to screen with)"
    share = defaults.SCREEN_HINT_SHARE
    n_screen = screen_size(K, float(settings.costs[SCREEN_LEVEL]), share, n_unknown)
    too_large = refit_too_large(n_screen, n_observations)
    if too_large is not None:
        return None, too_large
    if ratio >= limit:
        return share, (
            f"--screen auto: screening {share:g} of K; the model's cheap-level discrepancy sd "
            f"is {ratio:.2f} of its level-0 signal's, so the confirmation runs the screen's "
            f"lowest cheap results with certainty ({defaults.SCREEN_LEAD_SHARE:g} of its "
            "level-0 runs) rather than trust the model's ranking of them "
            "(docs/suite/screen_frontier.md); a cheap level unrelated to level 0 makes "
            "this screen cost about twice a uniform design's variance, and nothing before "
            "it tells the two apart: if yours is, plan with --screen off "
            "(docs/suite/unrelated_cheap.md)"
        )
    return share, (
        f"--screen auto: screening {share:g} of K; the model's cheap-level discrepancy sd is "
        f"{ratio:.2f} of its level-0 signal's (under {limit:g}: the screen had 0.31 to 1.06 "
        "times the unscreened variance there on the suite, docs/suite/screen_design.md)"
    )


def refit_too_large(n_screen: float, n_observations: int) -> str | None:
    """``--screen auto``'s second condition: why not to screen (None: screen) when the
    refit the confirmation rests on could not condition on every cheap run of the screen.

    Above ``fit``'s exact-conditioning cap (``fitting.condition_budget``; 14,654
    observations at the default 2 GiB) ``fit`` conditions on a subset, level-0 runs first,
    so screened segments would be confirmed without their own cheap run in the model, and
    scoring a large pool on that many observations takes minutes (about 90 s at 200,000
    segments and 14,000 observations, ``bench/bench_pipeline.py``).
    """
    from bams_cli.core.conditioning_budget import max_conditioned
    from bams_cli.pipeline.fitting import condition_budget

    cap = max_conditioned(condition_budget())
    total = n_observations + n_screen
    if cap is None or total <= cap:
        return None
    return (
        f"--screen auto: no screen; its {n_screen:,.0f} expected cheap runs and the log's "
        f"{n_observations:,} observations exceed the {cap:,} a refit conditions on exactly, "
        "and the screen's gain rests on that refit seeing every cheap run"
    )


def draw_screen(
    ws: Workspace,
    settings: Settings,
    *,
    number: int,
    ids: np.ndarray,
    p: np.ndarray,
    known: np.ndarray,
    K: float,
    share: float,
    leads: np.ndarray | None = None,
    lead_facts: dict[str, Any] | None = None,
    posterior: Any,
    confirm_prior: tuple[float, float],
    rng: np.random.Generator,
    meta: dict[str, Any],
    handoff_internal: bool,
) -> dict[str, Any]:
    """Draw S1, write the screen and the batch of its cheap runs (one transaction).

    ``p``: p_n over the pool at the plan's gamma; ``known``: which segments have a level-0
    result; ``leads``: the open leads (bool over the pool, ``estimation.open_leads``),
    screened and confirmed with certainty, and ``lead_facts`` the evidence that capped them; ``posterior``: what pi1 is planned under; ``confirm_prior``: the prior on lam
    the confirmation's pi2 will be planned under (recorded, so a refit cannot change it);
    ``meta``: what the screen's metadata shares with a plan's (seed, gamma ...).
    Returns the summary ``estimate --plan --screen --json`` prints.
    """
    from bams_cli.abandon import abandoned_mask
    from bams_cli.core import screen as sc
    from bams_cli.core.sampling import draw_poisson

    cost = check_share(share, settings)
    unknown = np.flatnonzero(~known)
    if unknown.size == 0:
        raise WorkspaceError(
            f"{ws.root}: every segment has a level-0 result; there is nothing to screen "
            "(drop --screen: the estimate is a census)"
        )
    lead = np.zeros(len(ids), bool) if leads is None else np.asarray(leads, bool) & ~known
    choice = sc.screen_design(
        p[unknown], K=K, cost=cost, share=share, posterior=posterior, leads=lead[unknown]
    )
    pi1 = choice.pi
    s1 = unknown[draw_poisson(pi1, rng)]
    obs = ws.read_observations().filter(pl.col("fidelity") == SCREEN_LEVEL)
    have = ids_in(ids[s1], obs[SID].to_numpy())
    gone = abandoned_mask(ws, ids, settings.n_levels)[s1, SCREEN_LEVEL]
    run = s1[~have & ~gone]
    n = len(ids)
    pi1_pool = np.ones(n)
    pi1_pool[unknown] = pi1
    screened = np.zeros(n, bool)
    screened[s1] = True
    batch = (ws.batch_numbers() or [0])[-1] + 1 if run.size else None
    # What the screen drew: its metadata and the summary both say it.
    facts = {
        "plan": number,
        "screen_share": share,
        "screen_level": SCREEN_LEVEL,
        "screen_cost": cost,
        "screen_expected": round(float(pi1.sum()), 6),
        "screen_design": choice.name,
        "screened": int(s1.size),
        "cheap_runs": int(run.size),
        "cheap_in_log": int(have.sum()),
        "cheap_abandoned": int((gone & ~have).sum()),
        "batch": batch,
        "leads_certain": int(lead.sum()),
        # The prior of pi1, which the confirmation's allowance keeps (``risk_prior``'s
        # ``recorded``), and the prior of the confirmation's pi2.
        "risk_prior": [float(v) for v in posterior.prior],
        "confirm_prior": [float(v) for v in confirm_prior],
    }
    screen_meta = {
        **meta, **facts, "series_K": K, "n_pool": n, "n_unknown": int(unknown.size),
        "lead_ids": ids[lead].astype(str).tolist(),
        "lead_evidence": lead_facts,
    }  # fmt: skip
    table = schemas.SCREEN.conform(
        pa.table(
            {
                SID: pa.array(ids.astype(str), pa.string()),
                "stratum": np.where(known, "known", "unknown").tolist(),
                "pi1": pi1_pool,
                "screened": screened,
                "p_n": np.asarray(p, np.float64),
            }
        ),
        screen_meta,
    )
    path = screen_path(ws, number)
    out: dict[str, Any] = {"batch": batch, "handoff": None, "results_template": None}
    with transaction() as tx:
        tx.write_parquet(path, table)
        if batch is not None:
            cols: dict[str, Any] = contract.contract_columns(
                "batch", batch, ids[run], np.full(run.size, SCREEN_LEVEL, np.int64), settings,
                ["screen"] * run.size,
            )  # fmt: skip
            cols |= {
                "delta_j": np.full(run.size, np.nan),
                "cluster": np.zeros(run.size, np.int64),
                "rank": np.arange(run.size, dtype=np.int64),
                "strategy": ["screen"] * run.size,
            }
            cols |= passthrough_columns(ws, run, taken=cols)
            bmeta = {
                "batch": batch,
                "seed": meta["seed"],
                "model_hash": meta["model_hash"],
                "options": {"strategy": "screen", "screen_for_plan": number,
                            "gamma": settings.gammas[0]},
                "j_before": None,
                "j_after": None,
            }  # fmt: skip
            btable = schemas.BATCH.conform(pa.table(cols), bmeta)
            bpath = schemas.batch_path(ws.root, batch)
            tx.write_parquet(bpath, btable)
            csv, template = write_handoff(
                tx, btable, bpath.with_suffix(".csv"), BATCH_INTERNAL, handoff_internal
            )
            out |= {"handoff": str(csv), "results_template": str(template)}
    then = (
        f"simulate {out['handoff']}, ingest the results, `bams-cli fit -w {ws.root}`, then "
        if batch is not None
        else "every screened segment's cheap result is in the log: "
    )
    return {
        "screen_file": str(path),
        **facts,
        **out,
        "samples_K": K,
        "level0_left": round(sc.confirm_budget(K, cost, int(run.size)), 6),
        "known_stratum": int(known.sum()),
        "seed": meta["seed"],
        "seed_source": meta["seed_source"],
        "notes": [
            n
            for n in [
                describe_leads(
                    int(lead.sum()),
                    lead_facts,
                    float(meta["plan_gamma"]),
                    of="the confirmation's level-0 runs",
                ),
                f"screen for plan {number}: {then}`bams-cli estimate --plan -w {ws.root}` "
                "draws the level-0 confirmation within the screen",
            ]
            if n
        ],
    }


def cheap_results(ws: Workspace, ids: np.ndarray) -> np.ndarray:
    """Each segment's cheap result (level ``SCREEN_LEVEL``) in the log, the mean of its
    results where it has several; NaN where it has none."""
    obs = (
        ws.read_observations()
        .filter(pl.col("fidelity") == SCREEN_LEVEL)
        .group_by(SID)
        .agg(pl.col("value").mean())
    )
    want = pl.DataFrame({SID: np.asarray(ids).astype(str), "_i": np.arange(len(ids))})
    joined = want.join(obs, on=SID, how="left").sort("_i")
    return joined["value"].cast(pl.Float64).fill_null(np.nan).to_numpy()


def read_screen(
    ws: Workspace, number: int, ids: np.ndarray
) -> tuple[pl.DataFrame, dict, np.ndarray]:
    """The screen confirmed by plan ``number``: its table, metadata, and each row's pool index.

    Raises WorkspaceError when the pool no longer holds a screened segment.
    """
    path = screen_path(ws, number)
    meta = read_metadata_json(path)
    table = pl.from_arrow(schemas.SCREEN.check(read_state(path), path))
    assert isinstance(table, pl.DataFrame)
    pos = pl.DataFrame({SID: ids.astype(str), "_i": np.arange(len(ids))})
    joined = table.join(pos, on=SID, how="left")
    lost = joined.filter(pl.col("_i").is_null())
    if lost.height == 0 and table.height != len(ids):
        # New segments would be in no stratum: never sampled, and the rate biased low.
        raise WorkspaceError(
            f"{path}: the pool has {len(ids) - table.height} segments more than when the "
            "screen was drawn; they are in none of its strata: start a new estimate with "
            "`estimate --plan --new-series`"
        )
    if lost.height:
        raise WorkspaceError(
            f"{path}: {lost.height} segments of the screen are no longer in the pool "
            f"({', '.join(lost[SID].head(3).to_list())}); start a new estimate with "
            "`estimate --plan --new-series`"
        )
    return joined, meta, joined["_i"].to_numpy().astype(np.int64)


def confirm_screen(
    ws: Workspace,
    settings: Settings,
    *,
    number: int,
    ids: np.ndarray,
    p_all: np.ndarray,
    g_plan: int,
    known_now: np.ndarray,
    samples: float | None,
    posterior: Any,
    confirm_posterior: Any,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """pi2 over S1 from the refitted p_n and the confirmation's draw.

    ``confirm_posterior`` plans pi2; ``posterior`` (the screen's prior) prices the
    interval's allowance for a failure no run has seen.

    Returns what ``estimation.estimate_plan`` writes as plan ``number``: ``sampled_idx``,
    ``known_idx``, ``pi`` (pi1 pi2 of the sampled), ``K2`` (the runs asked for on average,
    ``core.screen.confirm_size``), ``w_model``, ``w_max``,
    ``predicted_vs_uniform`` (``core.screen.predicted_vs_uniform``, None where undefined),
    ``n_unknown`` and the ``screen`` facts for the plan's metadata.
    """
    from bams_cli.core import design as dz
    from bams_cli.core import screen as sc
    from bams_cli.core.estimate import poisson_max_weight
    from bams_cli.core.sampling import draw_poisson

    table, smeta, index = read_screen(ws, number, ids)
    path = screen_path(ws, number)
    batch = smeta.get("batch")
    pend = ws.pending()
    if batch is not None and pend.height and bool((pend["batch"] == batch).any()):
        # Even with --allow-pending: pi2 drawn without the cheap runs K2 has paid for
        # would waste the screen.
        waiting = int((pend["batch"] == batch).sum())
        raise PendingResultsError(
            f"{path}: batch {batch}, the screen's cheap runs, awaits {waiting} results; "
            "ingest them (or abandon them) and refit before its confirmation"
        )
    K = float(smeta["series_K"])
    if samples is not None and not math.isclose(samples, K, rel_tol=1e-9):
        raise WorkspaceError(
            f"--samples: {path} screened for an estimate with K = {K:g}; its confirmation "
            "spends the rest (drop --samples, or pass the same K); pass --new-series to start "
            "a new estimate instead"
        )
    unknown_rows = (table["stratum"] == "unknown").to_numpy()
    U = index[unknown_rows]
    known_idx = index[~unknown_rows]
    newly = U[known_now[U]]
    if newly.size:
        raise WorkspaceError(
            f"{path}: {newly.size} segments the screen counted as unknown have a level-0 "
            f"result since ({', '.join(ids[newly[:3]].astype(str))}); the screen's design no "
            "longer holds: start a new estimate with `estimate --plan --new-series`"
        )
    pi1_U = table["pi1"].to_numpy()[unknown_rows]
    in_s1 = table["screened"].to_numpy()[unknown_rows]
    S1 = U[in_s1]
    pi1_S1 = pi1_U[in_s1]
    cost = float(smeta["screen_cost"])
    p2 = p_all[S1, g_plan]
    # The leads the screen took with certainty (pi1 = 1, so all in S1): confirmed so too.
    lead_U = ids_in(ids[U], np.asarray(smeta.get("lead_ids") or [], dtype=str))
    if np.any(lead_U & ~in_s1):
        raise WorkspaceError(f"{path}: a lead the screen took with certainty is not in it")
    own = np.zeros(S1.size, bool)
    if S1.size:
        K2 = min(sc.confirm_budget(K, cost, int(smeta["cheap_runs"])), float(S1.size))
        # The screen's own leads: its lowest cheap results, confirmed with certainty.
        own = sc.screen_leads(cheap_results(ws, ids[S1]), K2, taken=lead_U[in_s1])
        certain = lead_U[in_s1] | own
        pi2 = sc.confirm_design(p2, K2=K2, posterior=confirm_posterior, leads=certain).pi
    else:  # an empty screen has nothing to confirm: T = 0, its conditional mean
        K2, pi2 = 0.0, np.zeros(0)
    drawn = draw_poisson(pi2, rng)
    pi = sc.confirmed_pi(pi1_S1, pi2)
    # The interval's allowance for a failure no run has seen: a segment outside S1 is
    # priced as if confirmed as often as a screened segment of its risk is on average (the
    # "mean" allowance, ``core.screen.allowance_pi``; docs/suite/screen_design.md).
    # An open lead is confirmed with certainty: no unseen failure hides there, and its pi2
    # of 1 is not what a screened segment of its risk gets. So both allowances are taken
    # over U without the open leads (an empty rest of S1 prices at pi1, as an empty screen
    # does). The screen's own leads stay in: an unscreened segment, had it been screened,
    # would have been one as often as the screened ones of its risk were, so their pi2 of
    # 1 is part of what a screened segment of that risk gets. Leaving them out priced an
    # unseen failure at the non-leads' pi2 alone, and the suite's realised intervals were
    # 2 to 4 times as wide (toy2d 1.6 -> 6.5 times the rate), with no miss below to pay for.
    rest = ~lead_U
    pi1_r, s1_r, pi2_r = pi1_U[rest], in_s1[rest], pi2[~lead_U[in_s1]]
    n_certain = int(lead_U.sum()) + int(own.sum())
    w_model = []
    for g in range(p_all.shape[1]):
        risk = posterior.allowance_risk(p_all[U, g])[rest]
        w_model.append(dz.unseen_failure_weight(risk, sc.allowance_pi(pi1_r, s1_r, pi2_r, risk)))
    w_max = poisson_max_weight(sc.min_allowance_pi(pi1_r, s1_r, pi2_r))
    # What the checked model predicts of the confirmed design against uniform sampling of
    # K: the same yardstick as an unscreened plan's (``estimation.design_note``).
    predicted = sc.predicted_vs_uniform(
        confirm_posterior.risk(p_all[U, g_plan]), pi1_U, in_s1, pi2, K
    )
    return {
        "sampled_idx": S1[drawn],
        "known_idx": known_idx,
        "pi": pi[drawn],
        # The runs the confirmation asks for on average: K2, or more where the open leads
        # alone use K2 up (``core.screen.confirm_size``).
        "K2": sc.confirm_size(K2, n_certain, S1.size) if S1.size else 0.0,
        "w_model": w_model,
        "w_max": w_max,
        "predicted_vs_uniform": None if math.isnan(predicted) else round(predicted, 6),
        "n_unknown": int(U.size),
        "screen": {
            "file": str(path),
            "batch": smeta.get("batch"),
            "share": float(smeta["screen_share"]),
            "level": int(smeta["screen_level"]),
            "cost": cost,
            "series_K": K,
            "screened": int(S1.size),
            "cheap_runs": int(smeta["cheap_runs"]),
            "leads_certain": int(lead_U.sum()),
            "screen_leads": int(own.sum()),
            "level0_budget": K2,
            "confirm_prior": [float(v) for v in confirm_posterior.prior],
            "seed": smeta.get("seed"),
        },
    }
