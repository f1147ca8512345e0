"""Regenerate the sample data: synthetic stand-ins, not real fleet data.

    python sample_data/generate.py                    # the committed files
    python sample_data/generate.py av_like --n 45000 --out /tmp/av45k   # the paper's scale

Each data set gets a folder holding
  segments.parquet   what a team hands to `bams-cli embed-reduce`
  truth.parquet      ground truth per fidelity level (segment_id, value_0, value_1), used
                     only by `bams-cli simulate` and `report --truth`
  settings.toml      gammas and level costs, for `bams-cli init --settings-from`
The output is a deterministic function of the data set name, --n and --seed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bams_cli.core import synthetic
from bams_cli.settings import Settings, levels_from_costs

DEFAULT_N = {"toy2d": 20_000, "av_like": 2_000}
HERE = Path(__file__).resolve().parent


def write(name: str, n: int, seed: int, out: Path) -> None:
    pool = synthetic.toy2d(n, seed) if name == "toy2d" else synthetic.av_like(n, seed)
    out.mkdir(parents=True, exist_ok=True)
    ids = pa.array(pool.ids, pa.string())
    if name == "toy2d":
        cols = {"segment_id": ids, "x0": pool.features[:, 0], "x1": pool.features[:, 1]}
        dim = 2
    else:
        flat = pa.array(pool.features.astype(np.float32).ravel(), pa.float32())
        emb = pa.FixedSizeListArray.from_arrays(flat, pool.features.shape[1])
        cols = {"segment_id": ids, "embedding": emb}
        dim = 12
    for key, values in pool.extra.items():
        cols[key] = pa.array(np.round(values, 4))
    pq.write_table(
        pa.table(cols), out / "segments.parquet", compression="zstd", row_group_size=5_000
    )
    truth = {"segment_id": ids}
    for level in range(pool.truth.shape[1]):
        truth[f"value_{level}"] = pa.array(pool.truth[:, level])
    pq.write_table(pa.table(truth), out / "truth.parquet", compression="zstd")
    settings = Settings(
        gammas=(pool.gamma,),
        levels=levels_from_costs(pool.costs),
        seed=seed,
        embedding_dim=dim,
    )
    (out / "settings.toml").write_text(settings.to_toml())
    rate = float(np.mean(pool.truth[:, 0] <= pool.gamma))
    print(f"{name}: {n} segments, gamma {pool.gamma}, failure rate {rate:.4f} -> {out}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("names", nargs="*", help="toy2d and/or av_like (default: both)")
    parser.add_argument(
        "--n", type=int, help="pool size (default: 20000 for toy2d, 2000 for av_like)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="output folder (default: sample_data/<name>)")
    args = parser.parse_args()
    names = args.names or ["toy2d", "av_like"]
    for name in names:
        if name not in DEFAULT_N:
            parser.error(f"unknown data set {name!r}; choose from toy2d, av_like")
        out = args.out if args.out and len(names) == 1 else HERE / name
        write(name, args.n or DEFAULT_N[name], args.seed, out)


if __name__ == "__main__":
    main()
