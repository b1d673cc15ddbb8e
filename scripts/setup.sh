#!/usr/bin/env bash
# Installs what the ONNX path needs into the project's .venv: ONNX Runtime (its shared
# library, which `tcsense infer` loads at run time) and `onnx` + `numpy` for the validation
# scripts. Idempotent and quiet when everything is already there.
#
#   scripts/setup.sh            then: export ORT_DYLIB_PATH=$(scripts/setup.sh --print-lib)
#
# The binary finds the library through ORT_DYLIB_PATH, else .venv (this script's layout),
# so setting the variable is optional when running from the repository.
set -euo pipefail
cd "$(dirname "$0")/.."
ORT=onnxruntime==1.31.1
ONNX=onnx==1.23.0
PY=${PYTHON:-python3}

lib() { ls .venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.1.31.1 2>/dev/null | head -n 1; }

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
if [ -z "$(lib)" ] || ! .venv/bin/python -c 'import onnx, numpy' 2>/dev/null; then
  .venv/bin/python -m pip install --quiet --disable-pip-version-check "$ORT" "$ONNX" numpy >&2
fi
if [ -z "$(lib)" ]; then
  echo "setup.sh: $ORT installed but libonnxruntime.so.1.31.1 not found under .venv" >&2
  exit 1
fi
if [ "${1:-}" = "--print-lib" ]; then
  realpath "$(lib)"
fi
