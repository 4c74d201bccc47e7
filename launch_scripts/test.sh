#!/usr/bin/env bash
# Command 2: every test of patchwalk. Installs what is missing (launch_scripts/setup.sh: Debian cmake + C++
# compiler, a Python venv with the pinned ROS 2 Jazzy wheels, the patchwalk_msgs interface package built
# into it), builds the workspace, runs the Rust tests (cargo nextest, else cargo test) and the rclpy
# integration tests. Idempotent: each setup step is skipped when its inputs did not change. All DDS traffic stays on
# 127.0.0.1. The last line is `patchwalk tests: PASS (...)` or `patchwalk tests: FAIL (...)`.
#
# Environment: PATCHWALK_VENV (default .venv), PATCHWALK_PYTHON (interpreter for the venv),
# PATCHWALK_PYTEST_ARGS (extra pytest arguments), PATCHWALK_SKIP_RUST=1 / PATCHWALK_SKIP_PYTHON=1,
# PATCHWALK_NETNS=1 (rclpy tests inside `unshare -n`: a network namespace with only loopback),
# PATCHWALK_FUZZ_SECONDS=N (also fuzz each target N s, nightly), PATCHWALK_SKIP_FUZZ=1.
set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
START=$(date +%s)
VENV="${PATCHWALK_VENV:-$REPO/.venv}"
BUILD_DIR="$REPO/build"
LOG_DIR="$BUILD_DIR/test-logs"
mkdir -p "$LOG_DIR"

log() { printf '\n=== %s\n' "$*"; }
die() {
    echo "test.sh: $*" >&2
    echo "patchwalk tests: FAIL (setup: $*)"
    exit 1
}
# count WORD FILE: sum of the numbers before WORD on the runner's result lines ("12 passed", ...).
count() { grep -oE "[0-9]+ $1" "$2" 2>/dev/null | awk '{ n += $1 } END { print n + 0 }'; }

# Loopback-only DDS and a domain of our own for anything ROS the Rust tests might start.
export PATCHWALK_DDS_NETWORK=loopback
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"

# --- 1.-3. system packages, the venv with the ROS 2 Jazzy wheels, patchwalk_msgs built into it -------
# (launch_scripts/setup.sh, shared with launch_scripts/demo.sh; its failures end here with the FAIL line)
# shellcheck source=launch_scripts/setup.sh
source "$REPO/launch_scripts/setup.sh"

# --- 4. build -----------------------------------------------------------------------------------------
command -v cargo >/dev/null || die "cargo not found (install Rust: rustup)"
log "cargo build --release --workspace --all-targets"
cargo build --release --workspace --all-targets || die "cargo build failed"

# --- 4b. colcon build of the repository (ROS 2 workspace layout) ---------------------------------------
# patchwalk_msgs (ament_cmake) and the node packages (ament_cargo: colcon-ros-cargo + cargo-ament-build)
# into build/colcon/{build,install,log}; tests/test_colcon_install.py and tests/test_launch_files.py run
# against build/colcon/install. colcon gives every cargo package its own --target-dir
# (build/colcon/build/<pkg>); its release/ is a symlink to the release/ of the cargo build above, and
# `--workspace --all-targets` makes cargo-ament-build ask for exactly step 4's build (same crates, same
# features), so colcon compiles nothing again: it installs what step 4 built (instead of three
# per-package builds with their own feature sets). Needs colcon (the venv).
if [ "${PATCHWALK_SKIP_PYTHON:-0}" != 1 ]; then
    COLCON_DIR="$BUILD_DIR/colcon"
    CARGO_RELEASE="${CARGO_TARGET_DIR:-$REPO/target}/release"
    for pkg in patch_mapper step_executor terrain_sim; do
        mkdir -p "$COLCON_DIR/build/$pkg"
        [ "$(readlink "$COLCON_DIR/build/$pkg/release" 2>/dev/null)" = "$CARGO_RELEASE" ] \
            || { rm -rf "$COLCON_DIR/build/$pkg/release" && ln -s "$CARGO_RELEASE" "$COLCON_DIR/build/$pkg/release"; }
    done
    log "colcon build (msgs/ + the node packages into build/colcon/install)"
    COLCON_START=$(date +%s)
    # Run from build/colcon: colcon-ros-cargo writes its .cargo/config.toml into the working directory,
    # which must not be an ancestor of the packages (it would patch crates-io with the installed copies).
    (
        cd "$COLCON_DIR" &&
            PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" "$VENV/bin/colcon" --log-base log build \
                --base-paths "$REPO/msgs" "$REPO/nodes/perception/patch_mapper" "$REPO/nodes/execution/step_executor" \
                "$REPO/nodes/sim/terrain_sim" --build-base build --install-base install \
                --cmake-args -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF -DCMAKE_PREFIX_PATH="$VENV" \
                -DPython3_EXECUTABLE="$VENV/bin/python" --cargo-args --profile release --workspace --all-targets
    ) >"$LOG_DIR/colcon.log" 2>&1 || { grep -E '^(Failed|Aborted|error)' -A20 "$LOG_DIR/colcon.log" | head -60; die "colcon build failed (log: $LOG_DIR/colcon.log)"; }
    grep -E '^Summary:' "$LOG_DIR/colcon.log" | tail -1
    echo "colcon build: $(($(date +%s) - COLCON_START)) s"
fi

# --- 5. Rust tests ------------------------------------------------------------------------------------
RUST_PASSED=0
RUST_FAILED=0
RUST_STATUS=0
if [ "${PATCHWALK_SKIP_RUST:-0}" != 1 ]; then
    if cargo nextest --version >/dev/null 2>&1; then
        log "cargo nextest run --release --workspace"
        cargo nextest run --release --workspace --no-fail-fast 2>&1 | tee "$LOG_DIR/rust.log"
        RUST_STATUS=${PIPESTATUS[0]}
        grep -E '^ *Summary \[' "$LOG_DIR/rust.log" | tail -1 > "$LOG_DIR/rust.summary"
        RUST_PASSED=$(count passed "$LOG_DIR/rust.summary")
        RUST_FAILED=$(count failed "$LOG_DIR/rust.summary")
    else
        log "cargo test --release --workspace (cargo-nextest not installed)"
        cargo test --release --workspace --no-fail-fast 2>&1 | tee "$LOG_DIR/rust.log"
        RUST_STATUS=${PIPESTATUS[0]}
        grep -E '^test result: ' "$LOG_DIR/rust.log" > "$LOG_DIR/rust.summary"
        RUST_PASSED=$(count passed "$LOG_DIR/rust.summary")
        RUST_FAILED=$(count failed "$LOG_DIR/rust.summary")
    fi
    # A non-zero exit without a failed test (build error, crash) still counts as one failure.
    if [ "$RUST_STATUS" != 0 ] && [ "$RUST_FAILED" = 0 ]; then RUST_FAILED=1; fi
    # The crate docs' examples (the Surface Patch Library's five-line fit, ...).
    log "cargo test --release --workspace --doc"
    cargo test --release --workspace --doc >"$LOG_DIR/doc.log" 2>&1
    DOC_STATUS=$?
    grep -E '^test result: ' "$LOG_DIR/doc.log" > "$LOG_DIR/doc.summary"
    if [ "$DOC_STATUS" = 0 ]; then
        RUST_PASSED=$((RUST_PASSED + $(count passed "$LOG_DIR/doc.summary")))
    else
        RUST_FAILED=$((RUST_FAILED + $(count failed "$LOG_DIR/doc.summary") + 1))
        tail -30 "$LOG_DIR/doc.log"
    fi
    # Formatting and lints (workspace lints: no unwrap/expect/panic outside tests, unsafe denied).
    log "cargo fmt --all --check"
    if ! cargo fmt --all --check >"$LOG_DIR/fmt.log" 2>&1; then
        head -40 "$LOG_DIR/fmt.log"
        echo "test.sh: cargo fmt --all --check found unformatted code (run cargo fmt --all)"
        RUST_FAILED=$((RUST_FAILED + 1))
    fi
    log "cargo clippy --release --workspace --all-targets -- -D warnings"
    if ! cargo clippy --release --workspace --all-targets -- -D warnings >"$LOG_DIR/clippy.log" 2>&1; then
        grep -E '^(error|warning)' -A6 "$LOG_DIR/clippy.log" | head -60
        echo "test.sh: clippy found problems (log: $LOG_DIR/clippy.log)"
        RUST_FAILED=$((RUST_FAILED + 1))
    fi
fi

# --- 5b. fuzz smoke (nodes/fuzz, launch_scripts/fuzz.sh) -----------------------------------------------
# Replay mode (default): every stored input of every fuzz target (tests/data/fuzz/<target>/: seeds and
# the inputs that once crashed) ran above through the normal build, as the `stored_*_inputs_are_handled`
# cargo tests; building the fuzz targets with nightly and libFuzzer instrumentation compiles the whole
# dependency tree a second time, more than a CI run should spend on a smoke. PATCHWALK_FUZZ_SECONDS=N
# (N > 0) also runs each target N s with launch_scripts/fuzz.sh (needs the nightly toolchain);
# PATCHWALK_SKIP_FUZZ=1 skips the block.
if [ "${PATCHWALK_SKIP_RUST:-0}" != 1 ] && [ "${PATCHWALK_SKIP_FUZZ:-0}" != 1 ]; then
    FUZZ_TARGETS=$(find "$REPO/tests/data/fuzz" -mindepth 1 -maxdepth 1 -type d | wc -l)
    FUZZ_INPUTS=$(find "$REPO/tests/data/fuzz" -type f | wc -l)
    FUZZ_REPLAYED=$(grep -cE '(PASS .*stored_[a-z_]+_inputs_[a-z_]+$|stored_[a-z_]+_inputs_[a-z_]+ \.\.\. ok$)' "$LOG_DIR/rust.log" 2>/dev/null)
    log "fuzz smoke: replay mode ($FUZZ_INPUTS stored inputs of $FUZZ_TARGETS targets replayed by $FUZZ_REPLAYED cargo tests above)"
    if [ "${PATCHWALK_FUZZ_SECONDS:-0}" -gt 0 ] 2>/dev/null; then
        log "fuzz smoke: fuzzing mode, launch_scripts/fuzz.sh ${PATCHWALK_FUZZ_SECONDS} (nightly, libFuzzer)"
        if ! "$REPO/launch_scripts/fuzz.sh" "$PATCHWALK_FUZZ_SECONDS" >"$LOG_DIR/fuzz.log" 2>&1; then
            tail -30 "$LOG_DIR/fuzz.log"
            echo "test.sh: the fuzz smoke found a crash or did not build (log: $LOG_DIR/fuzz.log)"
            RUST_FAILED=$((RUST_FAILED + 1))
        fi
        grep -A20 '^fuzz.sh summary' "$LOG_DIR/fuzz.log"
    fi
fi

# --- 6. rclpy integration tests -----------------------------------------------------------------------
PY_PASSED=0
PY_FAILED=0
PY_STATUS=0
if [ "${PATCHWALK_SKIP_PYTHON:-0}" != 1 ]; then
    log "pytest tests/ (real rclpy against the node binaries, DDS on loopback)"
    # -n: one worker per core; every worker reserves its own ROS domain (tests/patchwalk_testing.py).
    # PATCHWALK_NETNS=1: run them in a fresh network namespace with only `lo` (needs root/unshare).
    NETNS=()
    if [ "${PATCHWALK_NETNS:-0}" = 1 ]; then
        unshare -n true 2>/dev/null || die "PATCHWALK_NETNS=1 but unshare -n is not permitted here"
        NETNS=(unshare -n sh -c 'ip link set lo up && exec "$@"' sh)
    fi
    # shellcheck disable=SC2086
    ${NETNS[@]+"${NETNS[@]}"} "$VENV/bin/python" -m pytest tests -n "$(nproc)" -p no:cacheprovider \
        -W ignore::DeprecationWarning ${PATCHWALK_PYTEST_ARGS:-} 2>&1 | tee "$LOG_DIR/python.log"
    PY_STATUS=${PIPESTATUS[0]}
    grep -E '^=+ .*[0-9]+ (passed|failed|errors?|no tests ran).* =+$' "$LOG_DIR/python.log" | tail -1 > "$LOG_DIR/python.summary"
    PY_PASSED=$(count passed "$LOG_DIR/python.summary")
    PY_FAILED=$(($(count failed "$LOG_DIR/python.summary") + $(count error "$LOG_DIR/python.summary")))
    # Non-zero exit without a counted failure (e.g. 5 = no tests collected) is a failure of the suite.
    if [ "$PY_STATUS" != 0 ] && [ "$PY_FAILED" = 0 ]; then PY_FAILED=1; fi
fi

# --- 7. verdict ---------------------------------------------------------------------------------------
ELAPSED=$(($(date +%s) - START))
TOTAL_PASSED=$((RUST_PASSED + PY_PASSED))
# Every counted failure fails the run: tests, doc tests, formatting and lints alike.
if [ "$RUST_FAILED" = 0 ] && [ "$PY_FAILED" = 0 ]; then
    echo
    echo "patchwalk: $TOTAL_PASSED passed, 0 failed"
    echo "patchwalk tests: PASS (rust $RUST_PASSED passed, python $PY_PASSED passed, ${ELAPSED} s)"
    exit 0
fi
echo
echo "patchwalk: $TOTAL_PASSED passed, $((RUST_FAILED + PY_FAILED)) failed"
echo "patchwalk tests: FAIL (rust $RUST_PASSED passed $RUST_FAILED failed, python $PY_PASSED passed $PY_FAILED failed, ${ELAPSED} s; logs in $LOG_DIR)"
exit 1
