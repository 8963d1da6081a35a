#!/usr/bin/env bash
# The quality bench one scene at a time (issue 18), so a long table survives an interrupted
# session: each (search, scene) writes tests/bench/quality/<search>-<scene>.json and its log,
# and a scene that runs past LIMIT seconds is stopped and recorded as such in its log.
#
#   SCENES=fig7b,fig7c SEEDS=1 SEARCHES=likelihood-differential LIMIT=900 bash tests/bench/quality-each.sh
#
# The searches and their settings are in searches.sh. BIN=path runs that binary instead of
# building one, so a long queue keeps measuring one build while the tree changes. TAG=name
# adds -name to the file names (two builds side by side); KEEP=folder keeps each run's pictures;
# TARGET_PHOTONS=n renders the targets with n photons per source instead of the bench's 200 000
# (and adds -target<n> to the file names).
# The whole script is read before it runs (one block, `exit` inside it): a queue that runs for
# hours is not changed by an edit of this file meanwhile.
{
set -uo pipefail
cd "$(dirname "$0")/../.."
SCENES=${SCENES:-fig7a,fig7b,fig7c,fig7d,fig7e,fig7f,fig7g,fig7h,fig7i,fig7j,fig7k,fig7l,phantom16}
SEEDS=${SEEDS:-1}
SEARCHES=${SEARCHES:-likelihood-differential paper}
LIMIT=${LIMIT:-900}
if [ -z "${BIN:-}" ]; then
  cargo build --release -q || exit 1
  BIN=target/release/scatterfarm
fi
mkdir -p tests/bench/quality
source tests/bench/searches.sh
for search in $SEARCHES; do
  search_flags "$search" || exit 1
  for scene in ${SCENES//,/ }; do
    name="tests/bench/quality/$search-$scene-seeds${SEEDS//,/-}${TARGET_PHOTONS:+-target$TARGET_PHOTONS}${TAG:+-$TAG}"
    keep=()
    target=()
    [ -n "${TARGET_PHOTONS:-}" ] && target=(--target-photons "$TARGET_PHOTONS")
    [ -n "${KEEP:-}" ] && keep=(--keep "$KEEP/$search-$scene${TAG:+-$TAG}")
    timeout "$LIMIT" "$BIN" bench reconstruct --engine cpu --scenes "$scene" \
      --seeds "$SEEDS" "${flags[@]}" "${target[@]}" "${keep[@]}" --out "$name.json" >/dev/null 2>"$name.log"
    rc=$?
    [ $rc -eq 124 ] && echo "stopped after $LIMIT s" >>"$name.log"
    echo "$search $scene rc=$rc"
  done
done
exit
}
