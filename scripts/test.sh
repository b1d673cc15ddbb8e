#!/usr/bin/env bash
# The whole test suite: unit tests, doctests and end-to-end tests of the binary on tiny problems.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo test --workspace --locked "$@"
