#!/usr/bin/env bash
# Command 2: every test of patchwalk. Installs what is missing (Debian cmake + C++ compiler, a Python
# venv with the pinned ROS 2 Jazzy wheels, the patchwalk_msgs interface package built into it), builds
# the workspace, runs the Rust tests (cargo nextest, else cargo test) and the rclpy integration tests.
# Idempotent: each setup step is skipped when its inputs did not change. All DDS traffic stays on
# 127.0.0.1. The last line is `patchwalk tests: PASS (...)` or `patchwalk tests: FAIL (...)`.
#
# Environment: PATCHWALK_VENV (default .venv), PATCHWALK_PYTHON (interpreter for the venv),
# PATCHWALK_PYTEST_ARGS (extra pytest arguments), PATCHWALK_SKIP_RUST=1 / PATCHWALK_SKIP_PYTHON=1,
# PATCHWALK_NETNS=1 (rclpy tests inside `unshare -n`: a network namespace with only loopback).
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
hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }
# count WORD FILE: sum of the numbers before WORD on the runner's result lines ("12 passed", ...).
count() { grep -oE "[0-9]+ $1" "$2" 2>/dev/null | awk '{ n += $1 } END { print n + 0 }'; }

# Loopback-only DDS and a domain of our own for anything ROS the Rust tests might start.
export PATCHWALK_DDS_NETWORK=loopback
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"

# --- 1. system packages --------------------------------------------------------------------------------
apt_install() {
    local sudo=""
    if [ "$(id -u)" != 0 ]; then
        command -v sudo >/dev/null || die "need root or sudo to apt-get install $*"
        sudo="sudo"
    fi
    log "apt-get install $*"
    $sudo apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$@" >/dev/null \
        || die "apt-get install $* failed"
}
missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v c++ >/dev/null || missing+=(g++)
command -v make >/dev/null || missing+=(make)
[ ${#missing[@]} -eq 0 ] || apt_install "${missing[@]}"

# --- 2. Python venv with the pinned ROS 2 Jazzy wheels -------------------------------------------------
pick_python() {
    if [ -n "${PATCHWALK_PYTHON:-}" ]; then echo "$PATCHWALK_PYTHON"; return; fi
    # The wheels exist for CPython 3.10-3.14 (x86_64 Linux; pins made on 3.11); the interface build
    # needs Python.h.
    for candidate in python3.11 python3.12 python3.10 python3.13 python3.14 python3; do
        command -v "$candidate" >/dev/null || continue
        if "$candidate" - <<'EOF' 2>/dev/null; then echo "$candidate"; return; fi
import os, sys, sysconfig
ok = (3, 10) <= sys.version_info[:2] <= (3, 14)
ok = ok and os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h"))
sys.exit(0 if ok else 1)
EOF
    done
}
if [ "${PATCHWALK_SKIP_PYTHON:-0}" != 1 ]; then
    REQ_HASH=$(hash_of tests/requirements.txt tests/constraints.txt)
    if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$VENV/.patchwalk-requirements" 2>/dev/null)" != "$REQ_HASH" ]; then
        PY=$(pick_python)
        if [ -z "$PY" ]; then
            apt_install python3 python3-venv python3-dev
            PY=$(pick_python)
        fi
        [ -n "$PY" ] || die "no CPython 3.10-3.14 with development headers found"
        log "venv $VENV ($($PY --version 2>&1)) with the ROS 2 Jazzy wheels"
        [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV" || die "cannot create $VENV"
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
            -r tests/requirements.txt -c tests/constraints.txt || die "pip install of tests/requirements.txt failed"
        # The wheels' exported CMake targets carry the include paths of the machine they were built on
        # (/opt/python/cpXY-cpXY/...); point them at this venv's interpreter and numpy.
        PYINC=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
        NPINC=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')
        grep -rl --include='*.cmake' '/opt/python/' "$VENV/share" 2>/dev/null | xargs -r sed -i -E \
            -e "s#/opt/python/cp[0-9]+-cp[0-9]+/include/python3\.[0-9]+#$PYINC#g" \
            -e "s#/opt/python/cp[0-9]+-cp[0-9]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#$NPINC#g"
        if grep -rq --include='*.cmake' '/opt/python/' "$VENV/share"; then
            die "unrewritten /opt/python paths left in $VENV/share"
        fi
        echo "$REQ_HASH" > "$VENV/.patchwalk-requirements"
    fi

    # --- 3. patchwalk_msgs built with plain cmake into the venv ----------------------------------------
    MSGS_HASH=$(hash_of "$VENV/.patchwalk-requirements" msgs/CMakeLists.txt msgs/package.xml msgs/msg/* msgs/srv/*)
    if [ "$(cat "$VENV/.patchwalk-msgs" 2>/dev/null)" != "$MSGS_HASH" ] \
        || ! "$VENV/bin/python" -c 'import patchwalk_msgs.msg, patchwalk_msgs.srv' 2>/dev/null; then
        log "building msgs/ (patchwalk_msgs) into $VENV"
        rm -rf "$BUILD_DIR/msgs"
        (
            export PATH="$VENV/bin:$PATH"
            cmake -S msgs -B "$BUILD_DIR/msgs" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
                -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
                -DPython3_EXECUTABLE="$VENV/bin/python" &&
                cmake --build "$BUILD_DIR/msgs" -j "$(nproc)" &&
                cmake --install "$BUILD_DIR/msgs"
        ) >"$LOG_DIR/msgs-build.log" 2>&1 || { tail -40 "$LOG_DIR/msgs-build.log"; die "msgs/ build failed (log: $LOG_DIR/msgs-build.log)"; }
        "$VENV/bin/python" -c 'import patchwalk_msgs.msg, patchwalk_msgs.srv' \
            || die "patchwalk_msgs built but does not import"
        echo "$MSGS_HASH" > "$VENV/.patchwalk-msgs"
    fi
fi

# --- 4. build -----------------------------------------------------------------------------------------
command -v cargo >/dev/null || die "cargo not found (install Rust: rustup)"
log "cargo build --release --workspace --all-targets"
cargo build --release --workspace --all-targets || die "cargo build failed"

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
if [ "$RUST_STATUS" = 0 ] && [ "$PY_STATUS" = 0 ]; then
    echo
    echo "patchwalk: $TOTAL_PASSED passed, 0 failed"
    echo "patchwalk tests: PASS (rust $RUST_PASSED passed, python $PY_PASSED passed, ${ELAPSED} s)"
    exit 0
fi
echo
echo "patchwalk: $TOTAL_PASSED passed, $((RUST_FAILED + PY_FAILED)) failed"
echo "patchwalk tests: FAIL (rust $RUST_PASSED passed $RUST_FAILED failed, python $PY_PASSED passed $PY_FAILED failed, ${ELAPSED} s; logs in $LOG_DIR)"
exit 1
