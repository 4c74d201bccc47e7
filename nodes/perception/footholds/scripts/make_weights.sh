#!/usr/bin/env bash
# Reproduces the shipped foothold weights (nodes/perception/footholds/weights/) and the evaluation:
# records simulated sequences with terrain_sim (training seeds and held-apart seeds, camera heights
# 0.35-0.55 m, tilts 30-60 deg, walking sway, Murray-Little noise), labels them with the fused patch
# pipeline, trains the CNN with and without tilt and the SVM, and runs `patch_mapper footholds eval`
# on the held-apart scenes and the real TUM frames.
#
#   nodes/perception/footholds/scripts/make_weights.sh            # everything
#   STAGE=eval nodes/perception/footholds/scripts/make_weights.sh # only the evaluation
# Environment: CARGO_TARGET_DIR (binaries), WORK (scratch, default build/footholds), TRAIN_SEEDS,
# TEST_SEEDS, FRAMES, EPOCHS, MAX_SAMPLES.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../../../.." && pwd)
BIN=${CARGO_TARGET_DIR:-$ROOT/target}/release
WORK=${WORK:-$ROOT/build/footholds}
WEIGHTS=$ROOT/nodes/perception/footholds/weights
TRAIN_SEEDS=${TRAIN_SEEDS:-$(seq 1 30)}
TEST_SEEDS=${TEST_SEEDS:-$(seq 101 106)}
FRAMES=${FRAMES:-15}
EPOCHS=${EPOCHS:-4}
MAX_SAMPLES=${MAX_SAMPLES:-2400}
STAGE=${STAGE:-all}
REAL=${REAL:-$ROOT/tests/data/tum_fr1_xyz}
mkdir -p "$WORK/sim"

if [[ $STAGE == all ]]; then
  (cd "$ROOT" && cargo build --release -p terrain_sim --bin terrain_sim -p patch_mapper --bin patch_mapper)
fi

# One sequence per seed; height, tilt and rock follow from the seed (deterministic).
record() {
  local seed=$1 out=$WORK/sim/seed_$1
  [[ -f $out/depth.txt ]] && return 0
  local base pitch rock
  base=$(awk -v s="$seed" 'BEGIN { printf "%.3f", 0.18 + 0.20 * ((s * 37) % 11) / 10 }')    # camera 0.35-0.55 m
  pitch=$(awk -v s="$seed" 'BEGIN { printf "%.4f", (30 + 30 * ((s * 53) % 13) / 12) * 3.14159265 / 180 }')  # 30-60 deg
  rock=$(( (seed * 7) % 12 ))
  "$BIN/terrain_sim" record "$out" --frames "$FRAMES" --sway --rock "$rock" \
    -p seed="$seed" -p motion.base_height_m="$base" -p motion.camera_pitch_rad="$pitch" \
    -p scene.untrained_rocks=8 -p scene.station_spacing_m=0.3 > /dev/null
}

train_dirs=(); test_dirs=()
for s in $TRAIN_SEEDS; do record "$s"; train_dirs+=("$WORK/sim/seed_$s"); done
for s in $TEST_SEEDS; do record "$s"; test_dirs+=("$WORK/sim/seed_$s"); done

if [[ $STAGE == all ]]; then
  "$BIN/patch_mapper" footholds label --out "$WORK/train.safetensors" --mirror --noisy-copies 1 "${train_dirs[@]}"
  "$BIN/patch_mapper" footholds train --set "$WORK/train.safetensors" --epochs "$EPOCHS" --max-samples "$MAX_SAMPLES" \
    --out "$WEIGHTS/foot_d.safetensors" --svm-out "$WEIGHTS/svm.json"
  "$BIN/patch_mapper" footholds train --set "$WORK/train.safetensors" --epochs "$EPOCHS" --max-samples "$MAX_SAMPLES" --no-angle \
    --out "$WEIGHTS/foot_d_noangle.safetensors"
fi
"$BIN/patch_mapper" footholds eval --test "${test_dirs[@]}" --real "$REAL" --out "$WORK/eval"
