#!/usr/bin/env bash
# Renders scored on the workers against counts sent to the coordinator: the likelihood search
# at grid 16 on fig7a (1152 × 1152 count matrices), 8 and 16 replay workers and jobs, each
# once with workers that score renders and once with workers that do not (the baseline), one
# after the other on the same host. Writes tests/bench/farm-scored/*.json.
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release -p scatterfarm
out=tests/bench/farm-scored
mkdir -p "$out"
for n in 8 16; do
  for mode in scored counts; do
    flag=()
    [ "$mode" = counts ] && flag=(--no-worker-scoring)
    target/release/scatterfarm bench farm --search likelihood --grid 16 --permutations 2 \
      --workers "$n" --jobs "$n" --seconds 10 --warmup 2 "${flag[@]}" \
      --json "$out/likelihood-grid16-w$n-$mode.json"
  done
done
