#!/usr/bin/env bash
# The main job end to end: installs ONNX Runtime into .venv (scripts/setup.sh), builds tcsense
# and runs `tcsense demo` — datasets, code design (random selection and deep sensing),
# code-memory export, TVAL3, ADMM-Net and U-Net training, ONNX export, ONNX Runtime — into
# demo-out/report.html (or DIR/report.html); then, where Chromium is installed, checks that the
# report's images all load and takes a screenshot (scripts/report_screenshot.sh).
#
#   scripts/demo.sh [DIR] [tcsense demo flags, e.g. --quick or --budget-minutes 20]
#
# Rerunning into the same DIR resumes; Ctrl-C stops cleanly.
set -euo pipefail
cd "$(dirname "$0")/.."
out=demo-out
if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then
  out=$1
  shift
fi
scripts/setup.sh
cargo build --release --locked
target/release/tcsense demo -o "$out" "$@"
if command -v chromium >/dev/null 2>&1; then
  scripts/report_screenshot.sh "$out"
fi
echo "report: $out/report.html"
