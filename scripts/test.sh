#!/usr/bin/env bash
# The whole test suite: unit tests, doctests and end-to-end tests of the binary on tiny problems.
# ONNX Runtime (for the export/inference tests) is installed into .venv first.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cargo test --workspace --locked "$@"
