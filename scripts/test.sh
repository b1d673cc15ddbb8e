#!/usr/bin/env bash
# The whole test suite: unit tests, doctests and end-to-end tests of the binary on tiny problems,
# then the Python package's pytest suite against a wheel built into a fresh venv.
# ONNX Runtime (for the export/inference tests) is installed into .venv first. Then the GPU
# path (cargo feature `gpu`, burn's wgpu backend) against the CPU path, on Mesa's software
# Vulkan driver where no GPU driver is installed (the tests skip where there is no adapter).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
# formatting is part of the suite (rustfmt.toml): a diff fails it
cargo fmt --all --check
# no incremental caches: a clean run never reuses them, and they doubled the size of target/
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
cargo test --workspace --locked "$@"
# the Python package: `pip install ./python` into a fresh venv (maturin, pytest and onnxruntime
# from PyPI), then its pytest suite against that wheel and the binary `cargo test` built. The
# dev profile reuses the test profile's builds of the dependencies whose features the module
# alone resolves the same (`pip install ./python` alone builds in release; `--profile test`
# would build a test harness).
rm -rf target/py-venv
"${PYTHON:-python3}" -m venv target/py-venv
MATURIN_PEP517_ARGS="--profile dev" target/py-venv/bin/pip install --quiet --disable-pip-version-check "./python[test]"
TCSENSE_BIN="$PWD/target/debug/tcsense" target/py-venv/bin/python -m pytest -q python/tests
# with a Vulkan driver installed the GPU tests must run (TCSENSE_REQUIRE_GPU), not skip
if scripts/setup_vulkan.sh; then
  export TCSENSE_REQUIRE_GPU=1
fi
# The feature resolves the whole dependency tree anew: a second build of every crate, in the
# unoptimised profile `gpu-test` (3 min instead of 17 on 2 cores; the tests are tiny) and its
# own target directory
CARGO_TARGET_DIR=target/gpu-test cargo test --locked --profile gpu-test -p tcsense-train --features gpu --test gpu "$@"
