#!/usr/bin/env bash
# Copy a training run's files into the zoo entry zoo/NAME (config, codes, weights, metrics,
# timing and the checkpoint; with learned codes also relaxed/ and start_codes.json, once the
# relaxed phase is done), keeping the entry's PROVENANCE.md, recipe.json and first_steps.csv. Safe while the
# run trains: the checkpoint is copied first and the metrics cut to its epoch.
#
#   scripts/zoo_snapshot.sh RUN NAME
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=$1
NAME=$2
DEST=zoo/$NAME
[ -f "$RUN/checkpoint/state.json" ] || { echo "error: $RUN/checkpoint/state.json: no checkpoint to snapshot" >&2; exit 2; }
TMP=$(mktemp -d "zoo/.${NAME//\//-}.XXXXXX") # NAME may be drafts/…
cp -r "$RUN/checkpoint" "$TMP/checkpoint"
EPOCH=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["epoch"])' "$TMP/checkpoint/state.json")
cp "$TMP/checkpoint/model.bpk" "$TMP/model.bpk"
for f in config.json codes.json; do cp "$RUN/$f" "$TMP/$f"; done
for f in metrics.csv timing.csv; do head -n $((EPOCH + 1)) "$RUN/$f" > "$TMP/$f"; done
# deep sensing (--learn-codes): the relaxed phase is a run of its own, and the codes it started from
if [ -d "$RUN/relaxed" ]; then
  cp -r "$RUN/relaxed" "$TMP/relaxed"
  cp "$RUN/start_codes.json" "$TMP/start_codes.json"
fi
for f in PROVENANCE.md recipe.json first_steps.csv; do [ -f "$DEST/$f" ] && cp "$DEST/$f" "$TMP/$f"; done
rm -rf "$DEST"
mv "$TMP" "$DEST"
echo "zoo/$NAME: epoch $EPOCH of $RUN"
