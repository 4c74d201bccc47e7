#!/usr/bin/env bash
# Reproduces the shipped foothold weights (nodes/perception/footholds/weights/) and the evaluation:
# records simulated sequences with terrain_sim from three sources (camera 0.35-0.55 m above the
# ground, tilted 30-60 deg, walking sway, Murray-Little noise), labels them with the fused patch
# pipeline, trains the CNN with and without tilt and the SVM, and runs `patch_mapper footholds eval`
# on the held-apart scenes and the real TUM frames.
#
# Sources and how training and evaluation are kept apart:
#   rocks   the rock table; training seeds 1-60, held-apart seeds 101-106 (other untrained rocks).
#   course  tests/data/heightmaps/terrain.png at 2 cm per pixel, heights 0-0.5 m (10 x 10 m: blocks,
#           walls, stepping stones, stairs, slopes, rough ground), in 5 m quadrants: training walks
#           start and look into the lower-left and upper-right quadrants, held-apart walks into the
#           other two. Each walk starts 1.2 m behind a point within 0.6 m of its quadrant's centre, so
#           its view (to 3.4 m ahead at 30 deg tilt) stays in the quadrant. Start, heading, camera
#           height and tilt follow from the seed.
#   stairs  tests/data/heightmaps/real_stairs_125cm.png (4.9 x 2.8 m, 0.19 m risers), held apart only
#           (a view sees the whole width of the flight, so it cannot be split): up or down the flight.
# Every seed of a held-apart set is > 100, every training seed < 100.
#
#   nodes/perception/footholds/scripts/make_weights.sh            # everything
#   STAGE=eval nodes/perception/footholds/scripts/make_weights.sh # only the evaluation
#   STAGE=label ...                                               # record and label only
# After new weights: PATCHWALK_WRITE_REFERENCE=1 cargo nextest run --release -p patchwalk_footholds
# --test shipped_weights rewrites weights/reference_predictions.json.
# Environment: CARGO_TARGET_DIR (binaries), WORK (scratch, default build/footholds), ROCK_TRAIN,
# ROCK_TEST, COURSE_TRAIN, COURSE_TEST, STAIRS_TRAIN, STAIRS_TEST (seed lists), FRAMES, EPOCHS,
# MAX_SAMPLES (0: all), LR_DECAY, DROPOUT, HOLE_COPIES, POSITIVE_SHARE (empty: the set's own shares), REAL.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../../../.." && pwd)
BIN=${CARGO_TARGET_DIR:-$ROOT/target}/release
WORK=${WORK:-$ROOT/build/footholds}
WEIGHTS=$ROOT/nodes/perception/footholds/weights
MAPS=$ROOT/tests/data/heightmaps
ROCK_TRAIN=${ROCK_TRAIN:-$(seq 1 60)}
ROCK_TEST=${ROCK_TEST:-$(seq 101 106)}
COURSE_TRAIN=${COURSE_TRAIN:-$(seq 1 60)}
COURSE_TEST=${COURSE_TEST:-$(seq 101 108)}
STAIRS_TRAIN=${STAIRS_TRAIN:-}
STAIRS_TEST=${STAIRS_TEST:-$(seq 101 106)}
FRAMES=${FRAMES:-15}
EPOCHS=${EPOCHS:-3}
MAX_SAMPLES=${MAX_SAMPLES:-0}
LR_DECAY=${LR_DECAY:-0.36}
DROPOUT=${DROPOUT:-0}
HOLE_COPIES=${HOLE_COPIES:-1}
POSITIVE_SHARE=${POSITIVE_SHARE:-}
STAGE=${STAGE:-all}
REAL=${REAL:-$ROOT/tests/data/tum_fr1_xyz}
mkdir -p "$WORK/sim/rocks" "$WORK/sim/course" "$WORK/sim/stairs"

if [[ $STAGE == all ]]; then
  (cd "$ROOT" && cargo build --release -p terrain_sim --bin terrain_sim -p patch_mapper --bin patch_mapper)
fi

# Camera height (m above the ground) and tilt (deg) of a seed: 0.35-0.55 m, 30-60 deg.
height_of() { awk -v s="$1" 'BEGIN { printf "%.3f", 0.35 + 0.20 * ((s * 37) % 11) / 10 }'; }
pitch_of() { awk -v s="$1" 'BEGIN { printf "%.2f", 30 + 30 * ((s * 53) % 13) / 12 }'; }

# Rock table: the camera's base height is the table-relative height minus the 0.17 m mount.
record_rocks() {
  local seed=$1 out=$WORK/sim/rocks/seed_$1
  [[ -f $out/depth.txt ]] && return 0
  local base pitch
  base=$(awk -v h="$(height_of "$seed")" 'BEGIN { printf "%.3f", h - 0.17 }')
  pitch=$(awk -v d="$(pitch_of "$seed")" 'BEGIN { printf "%.4f", d * 3.14159265 / 180 }')
  "$BIN/terrain_sim" record "$out" --frames "$FRAMES" --sway --rock $(( (seed * 7) % 12 )) \
    -p seed="$seed" -p motion.base_height_m="$base" -p motion.camera_pitch_rad="$pitch" \
    -p scene.untrained_rocks=8 -p scene.station_spacing_m=0.3 > /dev/null
}

# The course: quadrant (seed mod 2) of the training (seed < 100) or held-apart diagonal.
record_course() {
  local seed=$1 out=$WORK/sim/course/seed_$1
  [[ -f $out/depth.txt ]] && return 0
  local start heading
  read -r start heading < <(awk -v s="$seed" 'BEGIN {
    q = s % 2; if (s > 100) { qx = q; qy = 1 - q } else { qx = q; qy = q }
    h = (s * 67 + 11 * int(s / 8)) % 360; r = h * 3.14159265 / 180
    ox = 0.6 * (((s * 17) % 9) / 4 - 1); oy = 0.6 * (((s * 23) % 9) / 4 - 1)
    x = 5 * qx + 2.5 + ox - 1.2 * cos(r); y = 5 * qy + 2.5 + oy - 1.2 * sin(r)
    printf "%.3f,%.3f %d\n", x, y, h }')
  "$BIN/terrain_sim" record "$out" --frames "$FRAMES" --sway --terrain "$MAPS/terrain.png" \
    --metres-per-pixel 0.02 --height-range 0,0.5 --start "$start" --heading "$heading" \
    --camera-height "$(height_of "$seed")" --pitch "$(pitch_of "$seed")" -p seed="$seed" > /dev/null
}

# The stairs: along the flight, up (heading 180) or down (0), at a seeded place across it.
record_stairs() {
  local seed=$1 out=$WORK/sim/stairs/seed_$1
  [[ -f $out/depth.txt ]] && return 0
  local start heading
  read -r start heading < <(awk -v s="$seed" 'BEGIN {
    y = 0.5 + 1.8 * ((s * 29) % 7) / 6
    up = (s % 2 == 0); x = up ? 4.2 - 1.6 * ((s * 13) % 5) / 4 : 0.5 + 1.6 * ((s * 13) % 5) / 4
    h = (up ? 180 : 0) + 5 * ((s * 11) % 5 - 2)
    printf "%.3f,%.3f %d\n", x, y, h }')
  "$BIN/terrain_sim" record "$out" --frames "$FRAMES" --sway --terrain "$MAPS/real_stairs_125cm.png" \
    --height-range 0,1.25 --start "$start" --heading "$heading" \
    --camera-height "$(height_of "$seed")" --pitch "$(pitch_of "$seed")" -p seed="$seed" > /dev/null
}

train_dirs=(); test_dirs=()
for s in $ROCK_TRAIN; do record_rocks "$s"; train_dirs+=("$WORK/sim/rocks/seed_$s"); done
for s in $COURSE_TRAIN; do record_course "$s"; train_dirs+=("$WORK/sim/course/seed_$s"); done
for s in $STAIRS_TRAIN; do record_stairs "$s"; train_dirs+=("$WORK/sim/stairs/seed_$s"); done
for s in $ROCK_TEST; do record_rocks "$s"; test_dirs+=("$WORK/sim/rocks/seed_$s"); done
for s in $COURSE_TEST; do record_course "$s"; test_dirs+=("$WORK/sim/course/seed_$s"); done
for s in $STAIRS_TEST; do record_stairs "$s"; test_dirs+=("$WORK/sim/stairs/seed_$s"); done

if [[ $STAGE == all || $STAGE == label ]]; then
  [[ -f $WORK/train.safetensors ]] ||
    "$BIN/patch_mapper" footholds label --out "$WORK/train.safetensors" --mirror --noisy-copies 1 --hole-copies "$HOLE_COPIES" \
      --pictures "$WORK/label_pictures" "${train_dirs[@]}" | tee "$WORK/label.log"
fi
if [[ $STAGE == all ]]; then
  share=(); [[ -n $POSITIVE_SHARE ]] && share=(--positive-share "$POSITIVE_SHARE")
  subset=(); [[ $MAX_SAMPLES != 0 ]] && subset=(--max-samples "$MAX_SAMPLES")
  "$BIN/patch_mapper" footholds train --set "$WORK/train.safetensors" --epochs "$EPOCHS" --lr-decay "$LR_DECAY" --dropout "$DROPOUT" \
    "${subset[@]}" "${share[@]}" --out "$WEIGHTS/foot_d.safetensors" --svm-out "$WEIGHTS/svm.json" > "$WORK/train.log" &
  with_angle=$!
  "$BIN/patch_mapper" footholds train --set "$WORK/train.safetensors" --epochs "$EPOCHS" --lr-decay "$LR_DECAY" --dropout "$DROPOUT" \
    "${subset[@]}" "${share[@]}" --no-angle --out "$WEIGHTS/foot_d_noangle.safetensors" > "$WORK/train_noangle.log" &
  no_angle=$!
  wait "$with_angle" && wait "$no_angle"
  cat "$WORK/train.log" "$WORK/train_noangle.log"
fi
if [[ $STAGE == all || $STAGE == eval ]]; then
  tests=(); for d in "${test_dirs[@]}"; do tests+=(--test "$d"); done
  "$BIN/patch_mapper" footholds eval "${tests[@]}" --real "$REAL" --out "$WORK/eval" | tee "$WORK/eval.log"
fi
