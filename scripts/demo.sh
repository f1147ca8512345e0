#!/usr/bin/env bash
# The whole discovery loop on the toy2d sample data, one shell command per step.
# Usage: scripts/demo.sh [workspace-folder]   (make demo runs it with ./demo)
set -euo pipefail
WS=${1:-demo}
DATA=sample_data/toy2d
TRUTH=$DATA/truth.parquet
rm -rf "$WS"
mkdir -p "$WS"
RES="$WS/results"
mkdir -p "$RES"
step() { printf '\n\033[1m$ %s\033[0m\n' "$*"; "$@"; }

step bams-cli init -w "$WS" --settings-from "$DATA/settings.toml"
step bams-cli embed-reduce -w "$WS" "$DATA/segments.parquet" --columns 'x*' --method identity --no-standardize

# Batch 1: random, spread over both fidelities (no model yet).
step bams-cli select -w "$WS" --strategy random --mixed-fidelity --budget 10
for batch in 1 2 3; do
  if [ "$batch" -gt 1 ]; then
    step bams-cli select -w "$WS" --strategy bams --budget 5
  fi
  n=$(printf '%04d' "$batch")
  # The simulation team's part, played here by the sample data's ground truth.
  step bams-cli simulate "$WS/batches/batch-$n.parquet" --truth "$TRUTH" -o "$RES/results-$n.parquet"
  step bams-cli ingest-results -w "$WS" "$RES/results-$n.parquet"
  step bams-cli fit -w "$WS"
done

# Rate estimate (K = 200, about 2 p N as in the paper's synthetic protocol). By default
# (--screen auto) a study whose fitted cheap level tracks level 0, as toy2d's does, screens
# first: 0.3 of K buys cheap runs of a sample, a batch of the log; their results and a
# refit let the next --plan confirm within the screen at level 0. Elsewhere the same
# commands plan three level-0 stages, each stage's results checking the model before the next.
# Either way: plan, simulate, ingest, refit, until status names `estimate` itself.
step bams-cli estimate -w "$WS" --plan --samples 200
if [ -e "$WS/estimates/screen-0001.parquet" ]; then
  screen=$(ls "$WS"/batches/batch-*.parquet | tail -n 1)  # the screen's cheap runs
  step bams-cli simulate "$screen" --truth "$TRUTH" -o "$RES/screen-results.parquet"
  step bams-cli ingest-results -w "$WS" "$RES/screen-results.parquet"
  step bams-cli fit -w "$WS"
  step bams-cli estimate -w "$WS" --plan
fi
next_is_plan() {
  bams-cli status -w "$WS" --json | python -c \
    'import json, sys; c = json.load(sys.stdin)["next"]["command"] or ""; sys.exit(not c.endswith("--plan"))'
}
k=1
while [ -e "$WS/estimates/plan-$(printf '%04d' "$k").parquet" ]; do
  n=$(printf '%04d' "$k")
  step bams-cli simulate "$WS/estimates/plan-$n-handoff.csv" --truth "$TRUTH" -o "$RES/estimate-$n.parquet"
  step bams-cli ingest-results -w "$WS" "$RES/estimate-$n.parquet"
  step bams-cli fit -w "$WS"
  if next_is_plan; then  # a staged estimate's next stage
    step bams-cli estimate -w "$WS" --plan
  fi
  k=$((k + 1))
done
step bams-cli estimate -w "$WS"
step bams-cli report -w "$WS" --truth "$TRUTH"

echo
echo "demo workspace: $WS/"
ls -1 "$WS"
python - "$WS" <<'PY'
import json, sys
ws = sys.argv[1]
s = json.load(open(f"{ws}/report/summary.json"))
for e, truth in zip(s["estimates"], s["truth"]["rate"]):
    print(f"failure rate at gamma {e['gamma']:g}: {e['p_hat']:.5f} "
          f"({int(round(e['confidence'] * 100))}% interval {e['ci_low']:.5f} to {e['ci_high']:.5f}); "
          f"true rate {truth:.5f}")
print(f"report: {ws}/report/report.html  (summary: {ws}/report/summary.md, {ws}/report/summary.json)")
PY
