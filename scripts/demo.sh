#!/usr/bin/env bash
# The whole discovery loop on the toy2d sample data, one shell command per step.
# Usage: scripts/demo.sh [workspace-folder]   (make demo runs it with ./demo)
set -euo pipefail
WS=${1:-demo}
DATA=sample_data/toy2d
rm -rf "$WS"
mkdir -p "$WS/results"
step() { printf '\n\033[1m$ %s\033[0m\n' "$*"; "$@"; }

step bams-cli init -w "$WS" --settings-from "$DATA/settings.toml"
step bams-cli embed-reduce -w "$WS" "$DATA/segments.parquet" --columns 'x*' --method identity --no-standardize

echo
echo "demo workspace: $WS/"
ls -1 "$WS"
