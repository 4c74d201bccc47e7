#!/usr/bin/env bash
# Fuzz the inputs the nodes take from the world (nodes/fuzz, cargo-fuzz + libFuzzer):
#
#   launch_scripts/fuzz.sh [SECONDS] [TARGET...]
#
# Runs each target (all of `cargo fuzz list` when none is named) for SECONDS (default 60) with
# `-max_total_time`, one after the other, and prints per target the executions, exec/s, coverage
# (libFuzzer's `cov` edges), the working corpus (inputs / size) and crashes.
# Each target's working corpus is nodes/fuzz/corpus/<target>/, seeded from the stored corpus
# tests/data/fuzz/<target>/ (which `cargo test` replays on stable); crashing inputs go to
# nodes/fuzz/artifacts/<target>/. A long campaign: `launch_scripts/fuzz.sh 600`.
#
# Needs the nightly toolchain (`cargo +nightly`); cargo-fuzz is installed when missing. Environment:
# FUZZ_JOBS (parallel libFuzzer workers per target, default 1), FUZZ_SANITIZER (default none: the
# workspace denies unsafe code, and the build keeps debug assertions and overflow checks; `address`
# for the dependencies' unsafe code), FUZZ_RSS_MB (memory limit per exec, default 2048),
# FUZZ_TIMEOUT_S (one input taking longer is a hang, default 10), CARGO_TARGET_DIR (default
# nodes/fuzz/target). Exit status 1 if any target crashed.
set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
FUZZ_DIR="$REPO/nodes/fuzz"
SECONDS_PER_TARGET="${1:-60}"
shift $(($# > 0 ? 1 : 0))
case "$SECONDS_PER_TARGET" in '' | *[!0-9]*) echo "fuzz.sh: SECONDS must be a whole number, got '$SECONDS_PER_TARGET'" >&2; exit 2 ;; esac
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$FUZZ_DIR/target}"
SANITIZER="${FUZZ_SANITIZER:-none}"

cargo +nightly --version >/dev/null 2>&1 || { echo "fuzz.sh: no nightly toolchain (rustup toolchain install nightly)" >&2; exit 2; }
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    echo "fuzz.sh: installing cargo-fuzz (cargo install cargo-fuzz --locked)"
    cargo install cargo-fuzz --locked || { echo "fuzz.sh: cannot install cargo-fuzz" >&2; exit 2; }
fi
# `--fuzz-dir` right after the subcommand: what follows `--` in `run` goes to libFuzzer.
fuzz() {
    local subcommand="$1"
    shift
    cargo +nightly fuzz "$subcommand" --fuzz-dir "$FUZZ_DIR" "$@"
}

if [ $# -gt 0 ]; then TARGETS=("$@"); else mapfile -t TARGETS < <(fuzz list); fi
[ ${#TARGETS[@]} -gt 0 ] || { echo "fuzz.sh: no fuzz targets" >&2; exit 2; }

echo "fuzz.sh: building ${#TARGETS[@]} target(s) (nightly, sanitizer $SANITIZER, debug assertions)"
fuzz build -s "$SANITIZER" -a || { echo "fuzz.sh: build failed" >&2; exit 2; }

LOG_DIR="$FUZZ_DIR/logs"
mkdir -p "$LOG_DIR"
STATUS=0
SUMMARY=()
for target in "${TARGETS[@]}"; do
    corpus="$FUZZ_DIR/corpus/$target"
    artifacts="$FUZZ_DIR/artifacts/$target"
    mkdir -p "$corpus" "$artifacts"
    [ -d "tests/data/fuzz/$target" ] && cp -n "tests/data/fuzz/$target"/* "$corpus"/ 2>/dev/null
    before=$(find "$artifacts" -type f | wc -l)
    log="$LOG_DIR/$target.log"
    echo "=== $target: ${SECONDS_PER_TARGET} s"
    # -jobs makes libFuzzer write fuzz-<n>.log files in the working directory: only for FUZZ_JOBS > 1.
    parallel=()
    [ "${FUZZ_JOBS:-1}" -gt 1 ] && parallel=(-jobs="$FUZZ_JOBS" -workers="$FUZZ_JOBS")
    fuzz run -s "$SANITIZER" -a "$target" "$corpus" -- \
        -max_total_time="$SECONDS_PER_TARGET" -artifact_prefix="$artifacts/" -print_final_stats=1 \
        -rss_limit_mb="${FUZZ_RSS_MB:-2048}" -timeout="${FUZZ_TIMEOUT_S:-10}" \
        ${parallel[@]+"${parallel[@]}"} >"$log" 2>&1
    rc=$?
    [ "${FUZZ_JOBS:-1}" -gt 1 ] && cat fuzz-*.log >>"$log" 2>/dev/null && rm -f fuzz-*.log
    execs=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$log" | awk '{ n += $2 } END { print n + 0 }')
    rate=$(grep -oE 'stat::average_exec_per_sec: *[0-9]+' "$log" | awk '{ n += $2 } END { print n + 0 }')
    crashes=$(($(find "$artifacts" -type f | wc -l) - before))
    if [ "$rc" != 0 ] && [ "$crashes" = 0 ]; then crashes="? (exit $rc, see $log)"; fi
    cov=$(grep -oE '(DONE|pulse|NEW|REDUCE) +cov: [0-9]+' "$log" | tail -1 | awk '{ print $3 }')
    inputs=$(find "$corpus" -type f | wc -l)
    size=$(du -sk "$corpus" | awk '{ print $1 }')
    line=$(printf '%-24s executions %10s  exec/s %6s  cov %5s  corpus %5s inputs %6s kB  crashes %s' \
        "$target" "$execs" "$rate" "${cov:-?}" "$inputs" "$size" "$crashes")
    echo "$line"
    SUMMARY+=("$line")
    if [ "$crashes" != 0 ]; then
        STATUS=1
        grep -E '^(thread .* panicked|==[0-9]+== ERROR|SUMMARY|artifact_prefix|Test unit written)' "$log" | head -8
    fi
done
echo
echo "fuzz.sh summary (${SECONDS_PER_TARGET} s per target; crashing inputs in nodes/fuzz/artifacts/<target>/, logs in nodes/fuzz/logs/):"
printf '  %s\n' "${SUMMARY[@]}"
exit "$STATUS"
