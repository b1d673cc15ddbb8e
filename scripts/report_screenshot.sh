#!/usr/bin/env bash
# Render a demo report in headless Chromium (Debian's `chromium` package): check that every
# image of DIR/report.html decoded, then save a screenshot of its top.
#
#   scripts/report_screenshot.sh [DIR] [OUT.png] [HEIGHT]
#
# DIR defaults to demo-out, OUT.png to DIR/report.png, HEIGHT (pixels, width 1280) to 2200.
# Exit 1 when an image is missing or does not decode, 2 when Chromium is not installed.
set -euo pipefail
dir=${1:-demo-out}
out=${2:-$dir/report.png}
height=${3:-2200}
report="$dir/report.html"
if [ ! -s "$report" ]; then
  echo "$report: no report; run tcsense demo -o $dir first" >&2
  exit 2
fi
chrome=$(command -v chromium || command -v chromium-browser || command -v google-chrome || true)
if [ -z "$chrome" ]; then
  echo "Chromium not found: install it (Debian: apt-get install chromium)" >&2
  exit 2
fi
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
# no background networking: this machine's closed network refuses Chromium's own connections
flags=(--headless --no-sandbox --disable-gpu --no-first-run --disable-background-networking
       --disable-component-update --disable-sync --user-data-dir="$profile" --hide-scrollbars)
url="file://$(realpath "$report")"
# the report counts its decoded images on load and writes data-images="ok/all" on <body>
dom=$("$chrome" "${flags[@]}" --virtual-time-budget=15000 --dump-dom "$url" 2>/dev/null)
images=$(printf '%s' "$dom" | grep -o 'data-images="[0-9]*/[0-9]*"' | head -n 1 | sed 's/.*="\(.*\)"/\1/')
if [ -z "$images" ]; then
  echo "$report: the page did not finish loading in Chromium" >&2
  exit 1
fi
ok=${images%/*}
all=${images#*/}
if [ "$ok" != "$all" ] || [ "$all" = 0 ]; then
  echo "$report: $ok of $all images decoded in Chromium" >&2
  exit 1
fi
"$chrome" "${flags[@]}" --window-size=1280,"$height" --virtual-time-budget=15000 --screenshot="$out" "$url" >/dev/null 2>&1
if [ ! -s "$out" ]; then
  echo "Chromium wrote no screenshot to $out" >&2
  exit 1
fi
echo "$report: all $all images decoded; screenshot $out (1280x$height)"
