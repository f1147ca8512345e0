"""The workspace folder: where each state file lives and how it is read back.

```
<workspace>/
  settings.toml            study settings (human-readable)
  reducer.npz              fitted embedding reducer (arrays only, no pickle)
  segments.parquet         reduced pool: segment_id, z0..z{d-1}, pass-through columns
  observations.parquet     append-only observation log
  abandoned.parquet        append-only log of requests that will never come back
  model.json               fitted GP hyperparameters (human-readable)
  scores.parquet           per-segment posterior mean, sd and failure probabilities
  batches/batch-NNNN.parquet (+ .csv)   hand-off lists
  estimates/plan-NNNN.parquet (+ handoff csv), estimates/estimate-NNNN.json
  report/                  report.html, summary.json, summary.md
```
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from bams_cli.core.hyperparameter_values import checked_dict
from bams_cli.defaults import BUDGET
from bams_cli.errors import BamsError, SchemaError, StaleStateError, WorkspaceError
from bams_cli.settings import SETTINGS_FILE, Settings, load_settings
from bams_cli.state import schemas
from bams_cli.state.handoff import REQUEST_ID, request_ids
from bams_cli.state.io import read_metadata, read_state, read_state_schema

REDUCER_FILE = "reducer.npz"
ESTIMATE_FILE = "estimate-{k:04d}.json"
MODEL_FILE = "model.json"
COORD = re.compile(r"^z(\d+)$")


@dataclass(frozen=True)
class Workspace:
    """Paths and readers for one study folder."""

    root: Path

    # ---- paths -------------------------------------------------------------------------
    @property
    def settings_path(self) -> Path:
        return self.root / SETTINGS_FILE

    @property
    def reducer_path(self) -> Path:
        return self.root / REDUCER_FILE

    @property
    def segments_path(self) -> Path:
        return schemas.SEGMENTS.path(self.root)

    @property
    def observations_path(self) -> Path:
        return schemas.OBSERVATIONS.path(self.root)

    @property
    def abandoned_path(self) -> Path:
        return schemas.ABANDONED.path(self.root)

    @property
    def model_path(self) -> Path:
        return self.root / MODEL_FILE

    @property
    def scores_path(self) -> Path:
        return schemas.SCORES.path(self.root)

    @property
    def batches_dir(self) -> Path:
        return self.root / "batches"

    @property
    def estimates_dir(self) -> Path:
        return self.root / "estimates"

    @property
    def history_dir(self) -> Path:
        return self.root / "history"

    @property
    def report_dir(self) -> Path:
        return self.root / "report"

    def holds_state(self, path: Path) -> bool:
        """Whether ``path`` is (or would be) one of this workspace's own state files."""
        if not self.settings_path.exists():
            return False
        ws, path = Workspace(self.root.resolve()), path.resolve()
        files = (ws.settings_path, ws.reducer_path, ws.segments_path, ws.observations_path,
                 ws.model_path, ws.scores_path, ws.abandoned_path)  # fmt: skip
        folders = (ws.batches_dir, ws.estimates_dir, ws.history_dir, ws.report_dir)
        return path in files or path.parent in folders

    # ---- existence -----------------------------------------------------------------------
    def require_initialised(self) -> Settings:
        if not self.root.is_dir():
            raise WorkspaceError(
                f"{self.root}: no such workspace; create it with `bams-cli init -w {self.root}`"
            )
        return load_settings(self.root)

    def require_segments(self) -> None:
        if not self.segments_path.exists():
            raise WorkspaceError(
                f"{self.segments_path}: no segment pool yet; run "
                f"`bams-cli embed-reduce -w {self.root} SEGMENTS.parquet` first"
            )

    # ---- segments ------------------------------------------------------------------------
    def read_segments(self, columns: list[str] | None = None) -> pa.Table:
        self.require_segments()
        table = read_state(self.segments_path, columns=columns)
        return schemas.SEGMENTS.check(table, self.segments_path)

    def coordinate_columns(self, table: pa.Table | None = None) -> list[str]:
        if table is None:
            self.require_segments()
        names = (
            table.column_names if table is not None else read_state_schema(self.segments_path).names
        )
        coords = sorted((n for n in names if COORD.match(n)), key=lambda n: int(n[1:]))
        if not coords:
            raise SchemaError(self.segments_path, "no coordinate columns z0, z1, ...", column="z0")
        return coords

    def read_pool(self) -> tuple[np.ndarray, np.ndarray]:
        """Segment ids and reduced coordinates: (ids of shape (N,), X of shape (N, d))."""
        coords = self.coordinate_columns()
        table = self.read_segments([schemas.SEGMENT_ID, *coords])
        ids = table.column(schemas.SEGMENT_ID).to_numpy(zero_copy_only=False)
        X = np.column_stack([table.column(c).to_numpy() for c in coords]).astype(np.float64)
        return ids, X

    def pool_fingerprint(self) -> str:
        """Pool size and a hash of its segment ids and coordinates: what a model's scores
        line up with. Re-reducing the same segments (``embed-reduce --force``) changes it."""
        coords = self.coordinate_columns()
        table = self.read_segments([schemas.SEGMENT_ID, *coords])
        digest = hashlib.sha256("\x1f".join(table.column(0).to_pylist()).encode())
        digest.update("\x1f".join(coords).encode())
        for c in coords:
            digest.update(np.ascontiguousarray(table.column(c).to_numpy(), np.float64).tobytes())
        return f"{table.num_rows}:{digest.hexdigest()[:16]}"

    # ---- observations --------------------------------------------------------------------
    def read_observations(self, *, active_only: bool = True) -> pl.DataFrame:
        if not self.observations_path.exists():
            return pl.from_arrow(schemas.OBSERVATIONS.schema.empty_table())  # type: ignore[return-value]
        table = schemas.OBSERVATIONS.check(
            read_state(self.observations_path), self.observations_path
        )
        df = pl.from_arrow(table)
        assert isinstance(df, pl.DataFrame)
        return df.filter(pl.col("active")) if active_only else df

    def observations_hash(self) -> str:
        """Content hash of the active observations: what a model was fitted on."""
        obs = self.read_observations().select(schemas.SEGMENT_ID, "fidelity", "value")
        digest = hashlib.sha256()
        for sid, lvl, val in obs.sort([schemas.SEGMENT_ID, "fidelity", "value"]).iter_rows():
            digest.update(f"{sid}\x1f{lvl}\x1f{val!r}\x1e".encode())
        return digest.hexdigest()[:16]

    def estimate_inputs_hash(self, plans: list[int], gammas: list[float]) -> str:
        """Content hash of what an estimate of these plans at these gammas reads from the
        log: whether each segment a plan holds (sampled and known) has a level-0 result,
        and whether it fails at each gamma. ``estimate`` records it; ``status`` and
        ``report`` compare it with the log's now, so an estimate whose results were
        corrected across a gamma since, or whose abandoned runs were simulated after all,
        is not shown as current (a value corrected on the same side of every gamma changes
        nothing it computes; a run with a result cannot be abandoned)."""
        obs = self.read_observations().filter(pl.col("fidelity") == 0)
        obs = obs.select(schemas.SEGMENT_ID, "value")
        g = np.asarray(gammas, dtype=np.float64)
        digest = hashlib.sha256()
        digest.update(f"{[float(x) for x in g]!r}\x1e".encode())
        for k in plans:
            path = self.estimates_dir / f"plan-{k:04d}.parquet"
            held = pl.from_arrow(read_state(path, columns=[schemas.SEGMENT_ID]))
            assert isinstance(held, pl.DataFrame)
            rows = held.join(obs, on=schemas.SEGMENT_ID, how="left").sort(schemas.SEGMENT_ID)
            values = rows["value"].to_numpy()  # NaN where there is no result
            seen = ~np.isnan(values)
            fails = (values[:, None] <= g[None, :]) & seen[:, None]
            for sid, has, row in zip(rows[schemas.SEGMENT_ID].to_list(), seen, fails, strict=True):
                outcome = "".join("1" if f else "0" for f in row) if has else "-"
                digest.update(f"{k}\x1f{sid}\x1f{outcome}\x1e".encode())
        return digest.hexdigest()[:16]

    def estimate_out_of_date(self, k: int, doc: dict[str, Any] | None = None) -> bool:
        """Whether plan ``k``'s computed estimate (``doc``, read when not given) read
        outcomes the log no longer holds: its recorded ``inputs_hash`` against
        ``estimate_inputs_hash`` now. False for an estimate written before the record; a
        ``StaleStateError`` naming the file where its plans or gammas are not what
        ``estimate`` writes."""
        doc = self.read_estimate(k) if doc is None else doc
        recorded = doc.get("inputs_hash")
        if not isinstance(recorded, str):
            return False
        plans = (doc.get("staging") or {}).get("plans") or [k]
        gammas = [e.get("gamma") for e in doc["estimates"]]
        ok = all(isinstance(p, int) and not isinstance(p, bool) and p > 0 for p in plans)
        if not ok or not all(isinstance(x, (int, float)) for x in gammas):
            raise StaleStateError(
                f"{self.estimate_path(k)}: staging.plans or a gamma is not what `estimate` "
                f"writes; run `bams-cli estimate -w {shlex.quote(str(self.root))} "
                f"--plan-number {k}` to write it again"
            )
        return recorded != self.estimate_inputs_hash(plans, gammas)

    # ---- batches -------------------------------------------------------------------------
    def batch_numbers(self) -> list[int]:
        if not self.batches_dir.is_dir():
            return []
        found = []
        for p in self.batches_dir.glob("batch-*.parquet"):
            m = re.fullmatch(r"batch-(\d+)\.parquet", p.name)
            if m:
                found.append(int(m.group(1)))
        return sorted(found)

    def read_batch(self, n: int) -> pl.DataFrame:
        """Batch ``n``'s picks, with its number as ``batch`` and every pick's ``request_id``
        (derived from the row for a batch written before request ids existed)."""
        path = schemas.batch_path(self.root, n)
        table = schemas.BATCH.check(read_state(path), path)
        df = pl.from_arrow(table)
        assert isinstance(df, pl.DataFrame)
        if REQUEST_ID not in df.columns:
            df = df.with_columns(pl.Series(REQUEST_ID, request_ids("batch", n, df.height)))
        return df.with_columns(pl.lit(n, dtype=pl.Int64).alias("batch"))

    def read_batches(self) -> pl.DataFrame:
        frames = [
            self.read_batch(n).select(
                schemas.SEGMENT_ID, "fidelity", "batch", "cost", "strategy", REQUEST_ID
            )
            for n in self.batch_numbers()
        ]
        if not frames:
            return pl.DataFrame(
                schema={
                    schemas.SEGMENT_ID: pl.String,
                    "fidelity": pl.Int64,
                    "batch": pl.Int64,
                    "cost": pl.Float64,
                    "strategy": pl.String,
                    REQUEST_ID: pl.String,
                }
            )
        return pl.concat(frames)

    def read_plan_picks(self) -> pl.DataFrame:
        """Segments estimate plans sent to level-0 simulation: (segment_id, fidelity, plan,
        request_id), the request id derived from the row for plans written before them."""
        frames = []
        if self.estimates_dir.is_dir():
            for p in sorted(self.estimates_dir.glob("plan-*.parquet")):
                if not p.stem[5:].isdigit():
                    continue
                number = int(p.stem[5:])
                names = read_state_schema(p).names
                cols = [schemas.SEGMENT_ID, "stratum"] + (
                    [REQUEST_ID] if REQUEST_ID in names else []
                )
                df = pl.from_arrow(read_state(p, columns=cols))
                assert isinstance(df, pl.DataFrame)
                df = df.filter(pl.col("stratum") == "sampled")
                if REQUEST_ID not in df.columns:
                    df = df.with_columns(
                        pl.Series(REQUEST_ID, request_ids("plan", number, df.height))
                    )
                frames.append(
                    df.select(
                        schemas.SEGMENT_ID,
                        pl.lit(0, dtype=pl.Int64).alias("fidelity"),
                        pl.lit(number, dtype=pl.Int64).alias("plan"),
                        pl.col(REQUEST_ID).cast(pl.String),
                    )
                )
        if not frames:
            return pl.DataFrame(
                schema={
                    schemas.SEGMENT_ID: pl.String,
                    "fidelity": pl.Int64,
                    "plan": pl.Int64,
                    REQUEST_ID: pl.String,
                }
            )
        return pl.concat(frames)

    def requests(self) -> pl.DataFrame:
        """Every request of every hand-off list: (request_id, segment_id, fidelity, batch,
        plan), ``batch`` null on a plan's requests and ``plan`` null on a batch's."""
        keys = [REQUEST_ID, schemas.SEGMENT_ID, "fidelity"]
        batches = self.read_batches().select(*keys, "batch")
        plans = self.read_plan_picks().select(*keys, "plan")
        return pl.concat([batches, plans], how="diagonal")

    def selections(self) -> pl.DataFrame:
        """Every selected (segment_id, fidelity) with the latest batch and plan that chose it."""
        keys = [schemas.SEGMENT_ID, "fidelity"]
        batches = self.read_batches().group_by(keys).agg(pl.col("batch").max())
        plans = self.read_plan_picks().group_by(keys).agg(pl.col("plan").max())
        both = batches.join(plans, on=keys, how="full", coalesce=True)
        return both.sort("batch", "plan", *keys, nulls_last=True)  # one order, run to run

    def read_abandoned(self) -> pl.DataFrame:
        """The log of abandoned requests (``schemas.ABANDONED``), empty when there is none."""
        if not self.abandoned_path.exists():
            df = pl.from_arrow(schemas.ABANDONED.schema.empty_table())
        else:
            df = pl.from_arrow(
                schemas.ABANDONED.check(read_state(self.abandoned_path), self.abandoned_path)
            )
        assert isinstance(df, pl.DataFrame)
        return df

    def abandoned_open(self, kind: str, number: int) -> pl.DataFrame:
        """(segment_id, fidelity) pairs batch or plan ``number`` (``kind``) asked for, that
        were abandoned for it and have no result."""
        keys = [schemas.SEGMENT_ID, "fidelity"]
        gone = self.read_abandoned().filter(pl.col(kind) == number).select(*keys).unique()
        obs = self.read_observations().select(*keys).unique()
        return gone.join(obs, on=keys, how="anti")

    def pending(self) -> pl.DataFrame:
        """Selected (segment, fidelity) pairs with no active observation yet, whose latest
        batch or plan request has not been abandoned; ``batch`` (``plan``) is null where
        that request was abandoned."""
        keys = [schemas.SEGMENT_ID, "fidelity"]
        obs = self.read_observations().select(*keys).unique()
        # In the order of ``selections`` (a join keeps none): the tables and lists that
        # show them read the same from one run to the next.
        pend = self.selections().with_row_index("_asked").join(obs, on=keys, how="anti")
        gone = self.read_abandoned()
        if gone.height == 0 or pend.height == 0:
            return pend.sort("_asked").drop("_asked")
        for key in ("batch", "plan"):
            mark = gone.filter(pl.col(key).is_not_null()).select(*keys, key).unique()
            pend = pend.join(mark.with_columns(pl.lit(True).alias("_gone")), on=[*keys, key],
                             how="left")  # fmt: skip
            pend = pend.with_columns(
                pl.when(pl.col("_gone")).then(None).otherwise(pl.col(key)).alias(key)
            ).drop("_gone")
        keep = pl.col("batch").is_not_null() | pl.col("plan").is_not_null()
        return pend.filter(keep).sort("_asked").drop("_asked")

    # ---- estimates -----------------------------------------------------------------------
    def estimate_path(self, k: int) -> Path:
        return self.estimates_dir / ESTIMATE_FILE.format(k=k)

    def read_estimate(self, k: int) -> dict[str, Any]:
        """Plan ``k``'s computed estimate (``estimates/estimate-NNNN.json``), checked key by key.

        The report and ``status`` read every key below; a file that is not valid JSON, lacks
        one, or holds the wrong kind of value (a string for a number, NaN, a negative count)
        is a ``StaleStateError`` naming the file, the key and the command that rewrites it.
        """
        path = self.estimate_path(k)
        fix = (
            f"run `bams-cli estimate -w {shlex.quote(str(self.root))} --plan-number {k}` "
            "to write it again"
        )
        try:
            doc = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            why = " ".join(str(exc).split())[:120]
            raise StaleStateError(f"{path}: damaged, not valid JSON ({why}); {fix}") from None
        try:
            _check_estimate(doc)
        except _BadKey as exc:
            raise StaleStateError(f"{path}: {exc}; {fix}") from None
        return doc

    def first_batch_command(self) -> str:
        """The command that draws a study's first batch: random, over every level the
        study has, so that the first model sees level-0 and cheap runs of the same segments;
        on a pool too small for the default budget, every segment at every level.
        ``status``, ``fit`` and ``select`` name this one command."""
        try:
            costs = self.require_initialised().costs
        except BamsError:  # damaged settings: their own error comes from the command
            costs = (1.0,)
        mixed = " --mixed-fidelity" if len(costs) > 1 else ""
        budget = float(BUDGET)
        try:  # a pool smaller than the budget buys: every segment at every level it has
            n = pq.ParquetFile(self.segments_path).metadata.num_rows
            budget = min(budget, round(n * sum(costs), 6))  # select allows for the rounding
        except (OSError, pa.ArrowException):  # no pool yet, or a damaged one
            pass
        w = shlex.quote(str(self.root))  # a command to paste or run (status --json's next)
        return f"bams-cli select -w {w} --strategy random{mixed} --budget {budget:g}"

    # ---- model ---------------------------------------------------------------------------
    def read_model(self) -> dict[str, Any]:
        if not self.model_path.exists():
            # A study without a pool needs that first; one without results, a first batch.
            self.require_segments()
            first = (
                f"select a first batch (`{self.first_batch_command()}`), "
                "simulate it and ingest the results, then fit"
                if not self.observations_path.exists()
                else f"run `bams-cli fit -w {self.root}`"
            )
            raise WorkspaceError(f"{self.model_path}: no fitted model; {first}")
        try:
            model = json.loads(self.model_path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            model = exc
        if not isinstance(model, dict) or not isinstance(model.get("hyperparameters"), dict):
            raise StaleStateError(
                f"{self.model_path}: damaged (not a model written by fit); "
                f"run `bams-cli fit -w {self.root}` to write it again"
            )
        self._check_hyperparameters(model["hyperparameters"])
        return model

    def _check_hyperparameters(self, hyperparameters: dict[str, Any]) -> None:
        """Refuse a model.json whose hyperparameters no fit wrote (NaN, a negative noise, a
        lengthscale per dimension the pool does not have): every reader of the model, not
        only ``select``, names the file and the command that rewrites it."""
        try:
            hp = checked_dict(hyperparameters)
            wrong = []
            n_levels, hp_d = hp["noise"].size, hp["lengthscales0"].size
            try:
                levels = self.require_initialised().n_levels
                if n_levels != levels:
                    wrong.append(f"{n_levels} levels, the study has {levels}")
            except BamsError:  # damaged settings: their own error comes from the command
                pass
            if self.segments_path.exists():
                d = len(self.coordinate_columns())
                if hp_d != d:
                    wrong.append(f"d = {hp_d}, the pool has d = {d}")
            if wrong:
                raise ValueError(f"they are for {' and '.join(wrong)}")
        except (KeyError, ValueError, TypeError, OverflowError) as exc:  # 1e400 as an int
            what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
            raise StaleStateError(
                f"{self.model_path}: damaged hyperparameters ("
                f"{what.removeprefix('Hyperparameters: ')}); run `bams-cli fit -w {self.root}` "
                "to write it again"
            ) from None

    def require_fresh_model(self) -> dict[str, Any]:
        """The model, refusing it if the observation log changed since it was fitted."""
        return self.require_model(allow_newer_observations=False)

    def require_model(self, *, allow_newer_observations: bool) -> dict[str, Any]:
        """The model and its scores, which must describe the current pool.

        With ``allow_newer_observations`` a model fitted before the latest results is
        returned with ``fresh = False`` instead of refused: for readers that only report
        what the model said (the GP's estimate as of an estimate plan, the report).
        """
        model = self.read_model()
        current = self.observations_hash()
        fresh = model.get("observations_hash") == current
        if not fresh and not allow_newer_observations:
            fitted = int(sum(model.get("n_observations_per_level", [])))
            raise StaleStateError(
                f"{self.model_path}: {stale_log(fitted, self.read_observations().height)}; "
                f"run `bams-cli fit -w {self.root}`"
            )
        pool = self.pool_fingerprint()
        if model.get("pool") != pool:
            raise StaleStateError(
                f"{self.model_path}: fitted on a different segment pool "
                f"({model.get('pool')} != {pool}, e.g. after embed-reduce --apply); "
                f"run `bams-cli fit -w {self.root}`"
            )
        settings = self.require_initialised()
        if "gammas" in model and [float(g) for g in model["gammas"]] != [
            float(g) for g in settings.gammas
        ]:
            # The scores' p_<k> columns are read by position: after an edit of the gammas
            # they would answer for the old thresholds under the new ones' names.
            raise StaleStateError(
                f"{self.model_path}: fitted for gammas {model['gammas']}, but "
                f"{self.settings_path.name} now says {list(settings.gammas)}; "
                f"run `bams-cli fit -w {self.root}`"
            )
        scored = read_metadata(self.scores_path) if self.scores_path.exists() else {}
        if scored.get("observations_hash") != model.get("observations_hash"):
            raise StaleStateError(
                f"{self.scores_path}: missing or not written by the last fit; "
                f"run `bams-cli fit -w {self.root}`"
            )
        model["fresh"] = fresh
        return model


# ---- estimate files ---------------------------------------------------------------------------
class _BadKey(ValueError):
    """A key of a state JSON file that is missing or of the wrong kind."""


#: Per-gamma keys of an estimate file: what each must hold ("count": an integer >= 0).
_ESTIMATE_ROW = {
    "gamma": "number",
    "p_hat": "number",
    "se": "number or null",
    "ci_low": "number",
    "ci_high": "number",
    "confidence": "number",
    "rel_var": "number or null",
    "n_sampled": "count",
    "failures_sampled": "count",
    "failures_known": "count",
    "distinct_failures_found": "count",
    "variance_note": "text or null",
    "rel_var_note": "text or null",
}
_GP_ROW = {"gamma": "number", "gp_p_hat": "number", "gp_var_bound": "number"}


def _fits(value: Any, kind: str) -> bool:
    if value is None:
        return kind.endswith("or null")
    if kind.startswith("text"):
        return isinstance(value, str)
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    if kind == "count":
        return isinstance(value, int) and value >= 0
    return math.isfinite(value)


def _shown(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _check_rows(doc: dict[str, Any], key: str, spec: dict[str, str], optional: set[str]) -> None:
    rows = doc.get(key)
    if not isinstance(rows, list) or not rows:
        got = "nothing" if key not in doc else _shown(rows)
        raise _BadKey(f"key {key!r}: expected a non-empty list of objects, got {got}")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise _BadKey(f"key {key}[{i}]: expected an object, got {_shown(row)}")
        for name, kind in spec.items():
            if name not in row and name in optional:
                continue
            if name not in row:
                raise _BadKey(f"key {key}[{i}].{name}: missing (expected a {kind})")
            if not _fits(row[name], kind):
                raise _BadKey(f"key {key}[{i}].{name}: expected a {kind}, got {_shown(row[name])}")


def _check_estimate(doc: Any) -> None:
    """Raise ``_BadKey`` naming the first key of an estimate file that readers cannot use."""
    if not isinstance(doc, dict):
        raise _BadKey(f"expected a JSON object, got {_shown(doc)}")
    _check_rows(doc, "estimates", _ESTIMATE_ROW, {"variance_note", "rel_var_note"})
    _check_rows(doc, "gp", _GP_ROW, set())
    gp_exact = [row.get("gp_var_exact") for row in doc["gp"]]
    for i, value in enumerate(gp_exact):
        if value is not None and not _fits(value, "number"):
            raise _BadKey(f"key gp[{i}].gp_var_exact: expected a number, got {_shown(value)}")


def stale_log(fitted: int, now: int) -> str:
    """Why a model fitted on ``fitted`` results is stale for a log of ``now`` active ones."""
    if fitted == now:  # as many results, other values: `ingest-results --replace`
        return (
            f"the observation log changed after the last fit (results replaced since: "
            f"fitted on {fitted} results, the log holds as many, not all the same)"
        )
    return (
        f"the observation log changed after the last fit (fitted on {fitted} results, "
        f"the log now holds {now})"
    )
