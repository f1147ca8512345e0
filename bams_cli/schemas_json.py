"""JSON Schemas of every command's ``--json`` output and of ``report/summary.json``.

Written by hand from the commands' real outputs (``tests/test_schemas_json.py`` runs each
command and validates what it prints), so a script can rely on them: every key listed as
required is always there with that type. Outputs may carry more keys than a schema lists
(``additionalProperties`` is left open); a key that goes away or changes meaning raises
that output's ``schema_version``, which each output carries. ``bams-cli schema [NAME]``
prints them.

The schemas use a small subset of JSON Schema (draft 2020-12): ``type``, ``required``,
``properties``, ``additionalProperties``, ``items``, ``const``, ``enum``, ``minimum``.
"""

from __future__ import annotations

from typing import Any

from bams_cli.status import STATUS_SCHEMA_VERSION

DIALECT = "https://json-schema.org/draft/2020-12/schema"

#: Version of each output; bump one when a key changes meaning or goes away.
VERSIONS: dict[str, int] = {
    "init": 1,
    "embed-reduce": 1,
    "ingest-results": 2,
    "simulate": 1,
    "fit": 1,
    "select": 1,
    "estimate-plan": 2,
    "estimate-screen": 1,
    "estimate": 2,
    "report": 1,
    "status": STATUS_SCHEMA_VERSION,
    "summary.json": 1,
    "abandon": 1,
    "loop": 1,
}

Schema = dict[str, Any]

STR: Schema = {"type": "string"}
INT: Schema = {"type": "integer"}
COUNT: Schema = {"type": "integer", "minimum": 0}
NUM: Schema = {"type": "number"}
BOOL: Schema = {"type": "boolean"}
PATH: Schema = {"type": "string", "description": "a file or folder path"}
#: The settings' embedding_dim: embed-reduce's default --dim.
EMBEDDING_DIM: Schema = {
    "type": ["integer", "string"],
    "description": 'a number of dimensions, or "auto" (from the embedding\'s spectrum)',
}
ANY: Schema = {}


def nullable(schema: Schema) -> Schema:
    """``schema`` or null (JSON has no NaN: an undefined number is null)."""
    kind = schema["type"]
    return {**schema, "type": [*(kind if isinstance(kind, list) else [kind]), "null"]}


def array(items: Schema) -> Schema:
    return {"type": "array", "items": items}


def obj(required: dict[str, Schema], optional: dict[str, Schema] | None = None) -> Schema:
    """An object with these required keys, these optional ones, and possibly more."""
    return {
        "type": "object",
        "required": list(required),
        "properties": {**required, **(optional or {})},
    }


def mapping(values: Schema, keys: str) -> Schema:
    """An object used as a map, e.g. level number -> count (JSON keys are strings)."""
    return {"type": "object", "description": f"keys: {keys}", "additionalProperties": values}


def _scoring(required: dict[str, Schema] | None = None) -> Schema:
    """How a pool's sds were got (``core.gp.MFGP.moments``): fit's ``scoring``, select's
    ``pool_sds``."""
    return obj(
        {"method": STR, "rows": COUNT, **(required or {})},
        {
            "max_work": NUM,
            "bound_observations": COUNT,
            "near_thresholds": COUNT,
            "exact_sd_rows": COUNT,
            "decided_z": NUM,
            "p_sum": array(NUM),
            "kept_bound_error": array(NUM),
        },
    )


LEVELS: Schema = array(obj({"name": STR, "cost": NUM}))
PENDING: Schema = obj(
    {
        "count": COUNT,
        "by_batch": mapping(COUNT, "batch number"),
        "first": array(
            obj(
                {"segment_id": STR, "fidelity": INT, "batch": nullable(INT)},
                {"plan": nullable(INT)},
            )
        ),
    },
    {"by_plan": mapping(COUNT, "plan number")},
)
HYPERPARAMETERS: Schema = obj(
    {
        "mean": NUM,
        "outputscale0": NUM,
        "lengthscales0": array(NUM),
        "outputscales": array(NUM),
        "lengthscales": array(array(NUM)),
        "noise": array(NUM),
    },
    {"offsets": array(NUM), "scales": array(NUM)},
)
CHECKS: Schema = obj(
    {
        "loo_level0": obj(
            {},
            {
                "n": COUNT,
                "mean_z2": nullable(NUM),
                "max_abs_z": nullable(NUM),
                "p_value": nullable(NUM),
                "max_p_value": nullable(NUM),
                "of": COUNT,
            },
        ),
        "pairs": array(
            obj(
                {"level": INT, "n_pairs": COUNT},
                {
                    "sd_observed": nullable(NUM),
                    "sd_fitted": nullable(NUM),
                    "p_value": nullable(NUM),
                },
            )
        ),
    }
)
ESTIMATE_ROW: Schema = obj(
    {
        "gamma": NUM,
        "p_hat": NUM,
        "se": nullable(NUM),
        "ci_low": NUM,
        "ci_high": NUM,
        "confidence": NUM,
        "rel_var": nullable(NUM),
        "n_sampled": COUNT,
        "failures_sampled": COUNT,
        "failures_known": COUNT,
        "distinct_failures_found": COUNT,
    },
    {
        "variance_note": nullable(STR),
        "rel_var_note": nullable(STR),
        # The Horvitz-Thompson sum (staged: the stages' weighted sum), p_hat unless that fell
        # below the failures found or above the segments not seen to pass.
        "p_hat_unbiased": NUM,
        # estimate --failed-as bounds: the range over abandoned planned segments.
        "p_hat_low": NUM,
        "p_hat_high": NUM,
        "abandoned": COUNT,
    },
)
#: ``status`` ``latest_estimate`` and ``loop`` ``estimate``: the newest estimate's headline.
LATEST_ESTIMATE: Schema = obj(
    {
        "plan": INT,
        "file": PATH,
        "estimates": array(
            obj(
                {"gamma": NUM, "p_hat": NUM, "ci_low": NUM, "ci_high": NUM, "confidence": NUM},
                {"se": nullable(NUM), "p_hat_low": NUM, "p_hat_high": NUM},
            )
        ),
    },
    {"stages_done": INT, "stages": INT, "out_of_date": BOOL},
)

#: ``ingest-results`` and ``abandon``: the batches and plans partly answered, and the list
#: of each one's pending requests alone (``state.pending``; null when not current).
PENDING_LISTS: Schema = array(
    obj(
        {
            "list": STR,
            "pending": COUNT,
            "requests": COUNT,
            "abandoned": COUNT,
            "handoff": PATH,
            "pending_handoff": nullable(PATH),
        }
    )
)

REQUEST: Schema = obj(
    {"request_id": STR, "segment_id": STR, "fidelity": INT},
    {"batch": nullable(INT), "plan": nullable(INT)},
)
GP_ROW: Schema = obj(
    {"gamma": NUM, "gp_p_hat": NUM, "gp_var_bound": NUM}, {"gp_var_exact": nullable(NUM)}
)

_OUTPUTS: dict[str, tuple[str, Schema]] = {
    "init": (
        "bams-cli init --json",
        obj(
            {
                "workspace": PATH,
                "settings": PATH,
                "gammas": array(NUM),
                "levels": LEVELS,
                "seed": INT,
                "embedding_dim": EMBEDDING_DIM,
            },
            {"unchanged": BOOL, "warnings": array(STR)},
        ),
    ),
    "embed-reduce": (
        "bams-cli embed-reduce --json",
        obj(
            {
                "segments": PATH,
                "added": COUNT,
                "pool_size": COUNT,
                "method": {"enum": ["pca", "ipca", "autoencoder", "identity"]},
                "dim": INT,
                "passthrough_columns": array(STR),
            },
            {
                "input_dim": INT,
                "dim_choice": nullable(STR),
                "reconstruction_error": {"type": "object"},
                "unchanged": BOOL,
                "note": STR,
                "warnings": array(STR),
            },
        ),
    ),
    "ingest-results": (
        "bams-cli ingest-results --json",
        obj(
            {
                "ingested": COUNT,
                "already_ingested": BOOL,
                "pending": PENDING,
                "pending_lists": PENDING_LISTS,
                "not_run": obj(
                    {
                        "count": COUNT,
                        "first": array(
                            obj(
                                {"status": STR},
                                {
                                    "request_id": nullable(STR),
                                    "segment_id": nullable(STR),
                                    "fidelity": nullable(COUNT),
                                    "fidelity_given": nullable(STR),
                                },
                            )
                        ),
                    }
                ),
            },
            {
                "message": STR,
                "replaced": COUNT,
                "already_known": COUNT,
                "observations": PATH,
                "log_rows": COUNT,
                "log_active": COUNT,
                "level_names": array(STR),
                "by_fidelity": mapping(COUNT, "level number"),
                "abandoned": obj(
                    {"abandoned": COUNT, "already_abandoned": COUNT, "first": array(REQUEST)}
                ),
            },
        ),
    ),
    "simulate": (
        "bams-cli simulate --json (sample data only)",
        obj({"results": PATH, "rows": COUNT, "note": STR}),
    ),
    "fit": (
        "bams-cli fit --json (a fit, or with up_to_date: true the model fit left as it was)",
        obj(
            {
                "model": PATH,
                "scores": PATH,
                "observations": COUNT,
                "n_observations_per_level": array(COUNT),
                "log_marginal_likelihood": NUM,
                "log_posterior": NUM,
                "hyperparameters": HYPERPARAMETERS,
                "checks": CHECKS,
                "jitter": NUM,
                "transform": obj({"kind": STR}),
                "warnings": array(STR),
            },
            {
                "gp_rate_estimate": mapping(NUM, "gamma"),
                "level0_failures": mapping(COUNT, "gamma"),
                "conditioning": nullable(
                    obj(
                        {
                            "method": STR,
                            "conditioned_on": COUNT,
                            "observations": COUNT,
                            "memory_budget_bytes": nullable(INT),
                            "note": STR,
                        }
                    )
                ),
                "scoring": _scoring({"note": STR}),
                "up_to_date": {"const": True},
                "message": STR,
                # With up_to_date: warnings about the settings as they are now (also in
                # warnings), said again although the model is kept.
                "settings_warnings": array(STR),
            },
        ),
    ),
    "select": (
        "bams-cli select --json",
        obj(
            {
                "batch": INT,
                "handoff": PATH,
                "handoff_csv": PATH,
                "results_template": PATH,
                "strategy": STR,
                "picks": COUNT,
                "total_cost": NUM,
                "budget": NUM,
                "picks_per_level": mapping(COUNT, "level number"),
                "picks_per_cluster": mapping(COUNT, "cluster (-1: confirmation picks)"),
                "confirm_picks": COUNT,
                "confirm_leads": COUNT,
                "j_before": nullable(NUM),
                "j_after": nullable(NUM),
                "timings_s": mapping(NUM, "stage"),
            },
            {
                "unchanged": BOOL,
                "out": PATH,
                "warnings": array(STR),
                "selection_plan": obj(
                    {
                        "exact": BOOL,
                        "reason": STR,
                        "clusters": COUNT,
                        "candidates_kept": COUNT,
                        "candidates_offered": COUNT,
                    },
                    {
                        "max_rows_per_cluster": nullable(COUNT),
                        "max_candidates_per_cluster": nullable(COUNT),
                        "rows_in_j": nullable(COUNT),
                        "h_left_out": nullable(NUM),
                        "screen_rounds": nullable(COUNT),
                        "candidates_per_round": nullable(COUNT),
                        "workers": nullable(COUNT),
                        "workers_reason": STR,
                        "scheduler": STR,
                        "pool_sds": _scoring(),
                        "local_observations": nullable(COUNT),
                        "j_by_cluster": BOOL,
                    },
                ),
            },
        ),
    ),
    "estimate-plan": (
        "bams-cli estimate --plan --json",
        obj(
            {
                "plan": INT,
                "plan_file": PATH,
                "handoff": PATH,
                "results_template": PATH,
                "design": {"enum": ["poisson", "fixed", "with-replacement"]},
                "samples_K": NUM,
                "to_simulate": COUNT,
                "simulations_certain": COUNT,
                "known_stratum": COUNT,
                "simulations_saved_by_known_stratum": NUM,
                "gp_rate_estimate": NUM,
                "plan_gamma": NUM,
                "alpha": NUM,
                "defensive": NUM,
                "seed": INT,
                "seed_source": {"enum": ["study settings", "--seed", "stage 1's --seed"]},
                "series": INT,
                "stage": INT,
                "stages": INT,
                "series_K": NUM,
                "stage_shares": array(NUM),
                "stage_weights": array(NUM),
                "weighting": {"enum": ["calibrated", "uniform", "p^alpha", "screen"]},
                "predicted_vs_uniform": nullable({"type": "object"}),
                "model_check": obj(
                    {
                        "lam": NUM,
                        "lam_high": NUM,
                        "failures": COUNT,
                        "sampled": COUNT,
                        "plans": array(INT),
                    },
                    # since the prior on lam follows the fitted cheap level
                    {"prior": array(NUM)},
                ),
                "notes": array(STR),
                "warnings": array(STR),
            },
            {
                # open cheap-level leads this plan samples with certainty, and the series'
                # (since they were: ``pipeline.estimation.open_leads``)
                "leads_certain": COUNT,
                "series_leads": COUNT,
                "screen": obj(
                    {
                        "file": PATH,
                        "batch": nullable(INT),
                        "share": NUM,
                        "level": INT,
                        "cost": NUM,
                        "series_K": NUM,
                        "screened": COUNT,
                        "cheap_runs": COUNT,
                        # open leads confirmed with certainty (pi1 = pi2 = 1)
                        "leads_certain": COUNT,
                        # the screen's own leads: its lowest cheap results, confirmed
                        # with certainty (``core.screen.screen_leads``)
                        "screen_leads": COUNT,
                        "level0_budget": NUM,
                        # Beta(a, b) on lam that planned pi2, as the screen recorded it
                        "confirm_prior": array(NUM),
                        "seed": nullable(INT),
                    }
                ),
            },
        ),
    ),
    "estimate-screen": (
        "bams-cli estimate --plan --screen SHARE --json (the screen before a screened estimate)",
        obj(
            {
                "screen_file": PATH,
                "plan": INT,
                "batch": nullable(INT),
                "handoff": nullable(PATH),
                "results_template": nullable(PATH),
                "samples_K": NUM,
                "screen_share": NUM,
                "screen_level": INT,
                "screen_cost": NUM,
                "screen_expected": NUM,
                "screen_design": {"enum": ["calibrated", "uniform", "p^alpha", "leads"]},
                "screened": COUNT,
                "cheap_runs": COUNT,
                "cheap_in_log": COUNT,
                "cheap_abandoned": COUNT,
                # open cheap-level leads screened and confirmed with certainty
                "leads_certain": COUNT,
                # Beta(a, b) priors on lam: pi1's, and the confirmation's pi2's
                "risk_prior": array(NUM),
                "confirm_prior": array(NUM),
                "level0_left": NUM,
                "known_stratum": COUNT,
                "seed": INT,
                "seed_source": {"enum": ["study settings", "--seed"]},
                "notes": array(STR),
                "warnings": array(STR),
            }
        ),
    ),
    "estimate": (
        "bams-cli estimate --json (computing a plan's estimate)",
        obj(
            {
                "plan": INT,
                "design": {"enum": ["poisson", "fixed", "with-replacement", "staged"]},
                "samples_K": NUM,
                "staging": obj(
                    {
                        "series": INT,
                        "plans": array(INT),
                        "stages_done": COUNT,
                        "stages": COUNT,
                        "weights": array(NUM),
                        "series_K": NUM,
                        "note": nullable(STR),
                    }
                ),
                "estimates": array(ESTIMATE_ROW),
                "gp": array(GP_ROW),
                "gp_model": STR,
                "notes": array(STR),
                # what it read from the log; `status` and `report` compare it with now
                "inputs_hash": STR,
                "estimate_file": PATH,
                "earlier_estimate": nullable(
                    obj({"file": PATH}, {"confidence": nullable(NUM), "interval": nullable(STR)})
                ),
            },
            {
                "abandoned": obj(
                    {
                        "count": COUNT,
                        "failed_as": {"enum": ["bounds"]},
                        "segments": array(STR),
                        "note": STR,
                    }
                )
            },
        ),
    ),
    "report": (
        "bams-cli report --json",
        obj(
            {
                "report": PATH,
                "summary_json": PATH,
                "summary_md": PATH,
                "figures": array(STR),
                "notices": array(STR),
                "estimates": array(
                    obj({"gamma": NUM, "p_hat": NUM, "ci_low": NUM, "ci_high": NUM})
                ),
            }
        ),
    ),
    "status": (
        "bams-cli status --json",
        obj(
            {
                "workspace": PATH,
                "gammas": array(NUM),
                "levels": array(STR),
                "pool_size": nullable(COUNT),
                "observations": COUNT,
                "observations_per_level": array(COUNT),
                "batches": array(
                    obj(
                        {
                            "batch": INT,
                            "strategy": nullable(STR),
                            "picks": COUNT,
                            "cost": NUM,
                            "budget": nullable(NUM),
                            "pending": COUNT,
                            "abandoned": COUNT,
                            "handoff": PATH,
                            "pending_handoff": nullable(PATH),
                        },
                        {"written_at": nullable(STR)},
                    )
                ),
                "plans": array(
                    obj(
                        {
                            "plan": INT,
                            "sampled": COUNT,
                            "pending": COUNT,
                            "abandoned": COUNT,
                            "handoff": PATH,
                            "pending_handoff": nullable(PATH),
                            "estimate": nullable(PATH),
                        },
                        {"written_at": nullable(STR)},
                    )
                ),
                "pending": COUNT,
                "abandoned": COUNT,
                "model": nullable(
                    obj(
                        {"fresh": BOOL},
                        {"fitted_on": COUNT, "fitted_at": STR, "reason": nullable(STR)},
                    )
                ),
                "latest_estimate": nullable(LATEST_ESTIMATE),
                "commit_in_progress": BOOL,
                "finished_interrupted_commit": COUNT,
                "waiting_on_results": BOOL,
                "phase": {"enum": ["setup", "discovery", "estimate", "done"]},
                "next": obj(
                    {
                        "step": STR,
                        "command": nullable(STR),
                        "text": STR,
                        "alternatives": array(obj({"step": STR, "command": STR})),
                    },
                    {"handoffs": array(PATH)},
                ),
                "exit_code": {"enum": [0, 3]},
            }
        ),
    ),
    "summary.json": (
        "report/summary.json, written by bams-cli report",
        obj(
            {
                "tool_version": STR,
                "generated_at": STR,
                "workspace": PATH,
                "notices": array(
                    obj(
                        {
                            "kind": {
                                "enum": [
                                    "outdated_estimate",
                                    "stale_estimate",
                                    "stale_model",
                                    "no_model",
                                    "pending_batches",
                                    "pending_plan",
                                    "design_like_uniform",
                                ]
                            },
                            "severity": {"enum": ["warning", "info"]},
                            "text": STR,
                        }
                    )
                ),
                "study": obj(
                    {
                        "gammas": array(NUM),
                        "levels": LEVELS,
                        "seed": INT,
                        "embedding_dim": EMBEDDING_DIM,
                        "pool_size": COUNT,
                        "dim": INT,
                    }
                ),
                "simulation_spent": obj(
                    {
                        "per_level": mapping(obj({"count": COUNT, "cost": NUM}), "level number"),
                        "count": COUNT,
                        "cost": NUM,
                        # of count: results --replace superseded, kept in the log
                        "superseded": COUNT,
                    }
                ),
                "model": nullable(
                    obj(
                        {"hyperparameters": HYPERPARAMETERS, "fresh": BOOL},
                        {"checks": CHECKS, "warnings": array(STR)},
                    )
                ),
                "batches": array(
                    obj(
                        {
                            "batch": INT,
                            "strategy": nullable(STR),
                            "picks": COUNT,
                            "picks_per_level": mapping(COUNT, "level number"),
                            "picks_per_cluster": mapping(COUNT, "cluster"),
                            "cost": NUM,
                            "pending": COUNT,
                        },
                        {
                            "mean_f0": nullable(NUM),
                            "mean_f0_se": nullable(NUM),
                            "n_f0": COUNT,
                            "abandoned": COUNT,
                        },
                    )
                ),
                "estimates": array(ESTIMATE_ROW),
                "gp_estimate": array(GP_ROW),
                "confirmed_failures": array(
                    obj(
                        {
                            "segment_id": STR,
                            "observed_f0": NUM,
                            "fails_at_gamma": array(NUM),
                            "p_n": nullable(NUM),
                        }
                    )
                ),
                "diverse_failures": array(
                    obj({"segment_id": STR, "p_n": NUM}, {"mu": nullable(NUM)})
                ),
                "truth": nullable(
                    obj(
                        {
                            "rate": array(NUM),
                            "failures": array(COUNT),
                            "estimate_recall": array(nullable(NUM)),
                            "retention_recall": {"type": "object"},
                        }
                    )
                ),
                "figures": array(STR),
            }
        ),
    ),
    "abandon": (
        "bams-cli abandon --json",
        obj(
            {
                "abandoned": COUNT,
                "already_abandoned": COUNT,
                "unchanged": BOOL,
                "by_source": mapping(COUNT, "list: batch N or plan N"),
                "first": array(REQUEST),
                "log": PATH,
                "log_rows": COUNT,
                "pending": PENDING,
                "pending_lists": PENDING_LISTS,
            },
            {"message": STR},
        ),
    ),
    "loop": (
        "bams-cli loop --json",
        obj(
            {
                "workspace": PATH,
                "batches": COUNT,
                "plans": COUNT,
                "steps": array(
                    obj(
                        {"step": STR, "list": nullable(STR)},
                        {
                            # what each kind of step adds (``loop._run``)
                            "up_to_date": BOOL,
                            "picks": COUNT,
                            "results": PATH,
                            "failed": {
                                "type": "integer",
                                "description": "the simulator's "
                                "exit code; the list was simulated again",
                            },
                            "rejected": PATH,
                            "abandoned": COUNT,
                            "ingested": COUNT,
                            "to_simulate": COUNT,
                            "estimate_file": PATH,
                        },
                    )
                ),
                "unchanged": BOOL,
                "results_dir": PATH,
                "estimate_file": nullable(PATH),
                "estimate": nullable(LATEST_ESTIMATE),
            }
        ),
    ),
}

NAMES = tuple(_OUTPUTS)


def version(name: str) -> int:
    """The schema version of output ``name``."""
    return VERSIONS[name]


def schema(name: str) -> Schema:
    """The JSON Schema of output ``name`` (one of ``NAMES``), a fresh dict."""
    title, body = _OUTPUTS[name]
    body = {**body, "required": ["schema_version", *body["required"]]}
    body["properties"] = {"schema_version": {"const": VERSIONS[name]}, **body["properties"]}
    return {
        "$schema": DIALECT,
        "$id": f"bams-cli/{name}/v{VERSIONS[name]}",
        "title": title,
        **body,
    }


def all_schemas() -> dict[str, Schema]:
    return {name: schema(name) for name in NAMES}
