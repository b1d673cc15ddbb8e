#!/usr/bin/env bash
# Fuzz the readers of untrusted input for SECONDS each (default 60): the .npy reader, the
# codes JSON, the dataset manifest, the run config, the ONNX metadata, a code memory's
# registers.json and a sweep's sweep.json. Needs the nightly
# toolchain and cargo-fuzz (`cargo install cargo-fuzz`); not part of CI. Crashes land in
# fuzz/artifacts/TARGET/ and become regression tests under tests/.
#
#   scripts/fuzz.sh [SECONDS] [TARGET…]
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_EACH=${1:-60}
shift || true
TARGETS=("$@")
if [ ${#TARGETS[@]} -eq 0 ]; then
  TARGETS=(npy codes_json manifest run_config onnx_meta registers sweep_manifest)
fi
mkdir -p fuzz/corpus
for t in "${TARGETS[@]}"; do
  mkdir -p "fuzz/corpus/$t"
  # seeds: the project's own files of that kind
  case $t in
    npy) cp tests/fixtures/admm-net-run-v1/*.npy "fuzz/corpus/$t/" 2>/dev/null || true ;;
    codes_json) cp tests/fixtures/admm-net-run-v1/codes.json "fuzz/corpus/$t/" ;;
    run_config) cp tests/fixtures/admm-net-run-v1/config.json "fuzz/corpus/$t/" ;;
    manifest) cp fuzz/seeds/manifest.json "fuzz/corpus/$t/" ;;
    onnx_meta) cp fuzz/seeds/admm-net.onnx "fuzz/corpus/$t/" ;;
    registers) cp fuzz/seeds/registers.json "fuzz/corpus/$t/" ;;
    sweep_manifest) cp fuzz/seeds/sweep.json "fuzz/corpus/$t/" ;;
  esac
  echo "== $t: $SECONDS_EACH s"
  cargo +nightly fuzz run "$t" "fuzz/corpus/$t" -- -max_total_time="$SECONDS_EACH" -rss_limit_mb=4096 -malloc_limit_mb=2048 2>&1 | grep -E "^#[0-9]+ +DONE|^Done|ERROR|panicked|SUMMARY|Test unit written" || true
done
