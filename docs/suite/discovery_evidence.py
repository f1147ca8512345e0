"""Does the discovery batches' level-0 evidence move lam before stage 1? (issue 12, point 2)

    .venv/bin/python docs/suite/discovery_evidence.py PROBLEM 0-4

For each seed the suite's protocol runs through the tool (``benchmark.run_one``) up to the
estimate, as ``estimate_refit.py`` does. Each BAMS batch's level-0 picks become one piece of
evidence for ``core.design.risk_posterior``: their relative risk u = p_n / mean_U(p_n) under
the model that picked them (``history/scores-after-batch-(N-1).parquet``, U the segments
without a level-0 result then) and whether they failed. Printed: each batch's picks, then
lam's posterior (mean, 0.9 quantile) and stage 1's exact variance over a uniform design's of
the same size, from the prior alone (what ``estimate --plan`` uses today), with the
discovery evidence (anchored, as the estimate's stages are), and unanchored.
docs/suite/discovery_evidence.md holds a run.
"""

import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import polars as pl
from estimate_refit import suite_problem, workspaces_before_estimate

from bams_cli import defaults
from bams_cli.core import design as dz
from bams_cli.state.io import read_state
from bams_cli.state.workspace import Workspace


def main(problem, seeds):
    warnings.simplefilter("ignore")
    scratch = Path(tempfile.mkdtemp(prefix=f"probe-{problem}-"))
    prob = suite_problem(problem, scratch)
    truth, pos, gamma, K = prob.truth, prob.pos, prob.gamma, prob.K
    for seed, base in workspaces_before_estimate(problem, prob, seeds, scratch):
        ws = Workspace(base)
        obs = ws.read_observations()
        ev = []
        for b in ws.batch_numbers():
            snap = ws.history_dir / f"scores-after-batch-{b - 1:04d}.parquet"
            if not snap.exists():
                continue
            ids = (
                pl.from_arrow(read_state(base / "scores.parquet"))["segment_id"]
                .cast(pl.Utf8)
                .to_numpy()
            )
            p = pl.from_arrow(read_state(snap))["p_0"].to_numpy()
            assert p.size == ids.size
            before = (
                obs.filter((pl.col("fidelity") == 0) & (pl.col("batch") < b))["segment_id"]
                .cast(pl.Utf8)
                .to_list()
            )
            U = ~np.isin(ids, before)
            mean = float(p[U].mean())
            u = p / mean
            picks = (
                ws.read_batch(b)
                .filter(pl.col("fidelity") == 0)["segment_id"]
                .cast(pl.Utf8)
                .to_list()
            )
            idx = np.flatnonzero(np.isin(ids, picks))
            failed = truth[[pos[s] for s in ids[idx]]] <= gamma
            ev.append(dz.StageEvidence(u[idx], failed, dz.risk_norms(u[U]), mean))
            print(
                f"  batch {b}: {idx.size} level-0 picks, {int(failed.sum())} failed, u of picks {np.round(u[idx], 1).tolist()}",
                flush=True,
            )
        # stage-1 design from the final scores, prior vs discovery evidence
        sc = pl.from_arrow(read_state(base / "scores.parquet"))
        ids = sc["segment_id"].cast(pl.Utf8).to_numpy()
        p = sc["p_0"].to_numpy()
        known = np.isin(
            ids, obs.filter(pl.col("fidelity") == 0)["segment_id"].cast(pl.Utf8).to_list()
        )
        U = np.flatnonzero(~known)
        fail = truth[[pos[s] for s in ids[U]]] <= gamma
        K1 = defaults.STAGE1_SHARE * K
        var_u = int(fail.sum()) * (U.size - K1) / K1
        out = {"problem": problem, "seed": seed, "failures_in_U": int(fail.sum())}
        for name, post in (
            ("prior", dz.risk_posterior([])),
            ("disc", dz.risk_posterior(ev)),
            ("disc_unanchored", dz.risk_posterior(ev, anchor_sd=None)),
        ):
            pi = dz.choose_design(p[U], K=K1, posterior=post).pi
            out[name] = {
                "lam": round(post.lam_mean, 3),
                "lam_hi": round(post.lam_quantile(0.9), 3),
                "var_ratio": round(float(((1 - pi[fail]) / pi[fail]).sum()) / var_u, 3),
            }
        print(json.dumps(out), flush=True)
        shutil.rmtree(base)
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    lo, hi = sys.argv[2].split("-")
    main(sys.argv[1], list(range(int(lo), int(hi) + 1)))
