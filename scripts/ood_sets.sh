# The out-of-distribution test sets, sourced by scripts/ood.sh, scripts/lifetime_bench.sh,
# scripts/zoo_ood.sh, scripts/zoo_codes_compare.sh and scripts/codes_headroom.sh (one definition,
# so their tables measure the same scenes). Each set differs from the randomised generator in one
# thing — as close as the flags get to the paper's generator: the LiDAR sets fix the randomised
# generator's knobs to the paper's ranges but for the one under test. Needs B (the tcsense
# binary) and SIZE (HxW).

# lidar_test_sets PREFIX COUNT: PREFIX{standard,far,near,textures,dense-sheet}
lidar_test_sets() {
  local p=$1 L="$B dataset lidar --size $SIZE --force --count $2"
  local FIX="--noise-texture 0 --max-slopes 0 --ambient-range 0 --interreflection-strength 0 --sheet-transmission 0.6,0.9 --sheet-reflectance 0.002,0.02 --sheet-distance 0.3,0.7"
  $L --paper --seed 11 -o "${p}standard"
  $L --seed 12 --wall-range 0.93,0.97 --object-range 0.6,0.9 $FIX -o "${p}far"
  $L --seed 13 --wall-range 0.2,0.35 --object-range 0.25,0.6 $FIX -o "${p}near"
  $L --seed 14 --wall-range 0.7,0.9 --object-range 0.25,0.6 --noise-texture 1 --max-slopes 3 --ambient-range 0 --interreflection-strength 0 --sheet-transmission 0.6,0.9 --sheet-reflectance 0.002,0.02 --sheet-distance 0.3,0.7 -o "${p}textures"
  $L --seed 15 --wall-range 0.7,0.9 --object-range 0.25,0.6 --noise-texture 0 --max-slopes 0 --ambient-range 0 --interreflection-strength 0 --sheet-probability 1 --sheet-transmission 0.3,0.5 --sheet-reflectance 0.02,0.05 --sheet-distance 0.3,0.7 -o "${p}dense-sheet"
}

# motorcycle_set OUT: range and albedo from the Middlebury 2014 stereo ground truth (from the
# scikit-image wheel, fetched from PyPI into OUT/wheels) as OUT/lidar-test-motorcycle
motorcycle_set() {
  local out=$1 skimage=scikit-image==0.26.0
  if [ ! -x .venv/bin/python ]; then python3 -m venv .venv; fi
  .venv/bin/pip install -q numpy pillow
  mkdir -p "$out/wheels"
  ls "$out/wheels"/scikit_image-*.whl >/dev/null 2>&1 || .venv/bin/pip download -q --no-deps "$skimage" -d "$out/wheels"
  .venv/bin/python scripts/middlebury_motorcycle.py "$out/wheels"/scikit_image-*.whl "$out"
  $B dataset import --depth "$out/range.npy" --albedo "$out/albedo.npy" --force -o "$out/lidar-test-motorcycle"
}

# flim_test_sets PREFIX COUNT: PREFIX{standard,onset-0ns,onset-30ns,irf-1.5ns,long-lifetimes,background}
# (the paper's lifetimes and onset with one change each; three lifetimes drawn in 0.5–3.5 ns)
flim_test_sets() {
  local p=$1 F="$B dataset flim --size $SIZE --force --count $2"
  local FIX="--onset-ns 2 --lifetimes 3 --tau-ns 0.5,3.5 --background 0 --brightness 1"
  $F --paper --seed 11 -o "${p}standard"
  $F --paper --onset-ns 0 --seed 12 -o "${p}onset-0ns"
  $F --paper --onset-ns 30 --seed 13 -o "${p}onset-30ns"
  $F $FIX --irf-fwhm-ns 1.5 --seed 14 -o "${p}irf-1.5ns"
  $F --onset-ns 2 --lifetimes 1,3 --tau-ns 4,8 --irf-fwhm-ns 0 --background 0 --brightness 1 --seed 15 -o "${p}long-lifetimes"
  $F --onset-ns 2 --lifetimes 3 --tau-ns 0.5,3.5 --brightness 1 --irf-fwhm-ns 0 --background 0.05 --seed 16 -o "${p}background"
}

# lidar_sets_in OUT COUNT: sets LIDAR_SETS, unless given, to OUT/lidar-sets, made there once
# (lidar_test_sets and the motorcycle; a .done mark says they are whole)
lidar_sets_in() {
  [ -n "${LIDAR_SETS:-}" ] && return
  LIDAR_SETS=$1/lidar-sets
  if [ ! -f "$LIDAR_SETS/.done" ]; then
    mkdir -p "$LIDAR_SETS"
    lidar_test_sets "$LIDAR_SETS/" "$2"
    motorcycle_set "$LIDAR_SETS"
    touch "$LIDAR_SETS/.done"
  fi
}

# flim_sets_in OUT COUNT: the same for FLIM_SETS (flim_test_sets in OUT/flim-sets)
flim_sets_in() {
  [ -n "${FLIM_SETS:-}" ] && return
  FLIM_SETS=$1/flim-sets
  if [ ! -f "$FLIM_SETS/.done" ]; then
    mkdir -p "$FLIM_SETS"
    flim_test_sets "$FLIM_SETS/" "$2"
    touch "$FLIM_SETS/.done"
  fi
}
