#!/usr/bin/env bash
# The quality bench at the truth's resolution (issue 18): every search named in SEARCHES on the
# scenes in SCENES, seeds in SEEDS, each run's JSON in tests/bench/quality-<search>.json.
# Geometry and targets are bench reconstruct's defaults: each scene's own grid, 32 positions ×
# 5 directions, 200 000 target photons per source (the same targets for every search).
#
#   SCENES=fig7a,fig7d SEEDS=1,2,3 SEARCHES="likelihood-differential paper" bash tests/bench/quality.sh
#
# likelihood-differential is the likelihood search with differential screening (CPU engine):
# sweeps of 102 400 photons per source, confirmations of 204 800, up to 24 sweeps.
set -euo pipefail
cd "$(dirname "$0")/../.."
SCENES=${SCENES:-fig7a,fig7b,fig7c,fig7d,fig7e,fig7f,fig7g,fig7h,fig7i,fig7j,fig7k,fig7l,phantom16}
SEEDS=${SEEDS:-1,2,3}
SEARCHES=${SEARCHES:-likelihood-differential paper}
cargo build --release -q
source tests/bench/searches.sh
for search in $SEARCHES; do
  search_flags "$search" || exit 1
  target/release/scatterfarm bench reconstruct --engine cpu --scenes "$SCENES" --seeds "$SEEDS" \
    "${flags[@]}" --out "tests/bench/quality-$search.json"
done
