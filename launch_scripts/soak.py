#!/usr/bin/env python3
"""Soak run: the whole simulated system with auto-execution for a long time, sampled every 10 s.

Starts the simulated servo bus (`step_executor sim-bus`), terrain_sim (30 Hz depth + IMU), patch_mapper and
step_executor (DDS on loopback, a domain of its own), trains the trained rocks of the four-rock scene as
launch_scripts/experiment.py does, then runs experiment trials (place the robot, reset the mapper, arm,
auto-execution plays the matched motion) in a loop, trained and untrained rocks in turn, until the time is
up. Every `--period` seconds it samples, per node, RSS and CPU (from /proc), and for the system the
PatchArray output rate, the depth-stamp -> PatchArray arrival latency (p50/p99 over the period), the
mapper's dropped/rejected frames, the executor's faults, and the ERROR/WARN lines of every log.

Output (in `--out`, default build/soak): `soak.csv` (one row per sample), `soak.png` (RSS, CPU, rate and
latency over time), `summary.json`, and the logs. The summary checks the goals: output rate drop <= 1 %
(the last 10 % of the run against the first 10 % after warm-up), RSS growth < 5 % after warm-up, no
error; the exit code is 0 when they hold. Ctrl-C ends the run early (after the current trial) with the
summary of what was sampled. The rate and latency figures mean something only on an otherwise quiet
machine.

    .venv/bin/python launch_scripts/soak.py                     # 60 min
    .venv/bin/python launch_scripts/soak.py --minutes 5         # a short one

The binaries come from the release build (`cargo build --release --workspace`, CARGO_TARGET_DIR honoured).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "launch_scripts"))

import patchwalk_testing as pw  # noqa: E402  (the fixture library: binaries, NodeProcess, RosHarness)

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def proc_sample(pid: int) -> tuple[float, float]:
    """(RSS in MB, CPU seconds used so far) of a process, from /proc."""
    with open(f"/proc/{pid}/statm") as f:
        rss_pages = int(f.read().split()[1])
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu_s = (int(fields[11]) + int(fields[12])) / CLOCK_TICKS  # utime + stime
    return rss_pages * PAGE_BYTES / 1e6, cpu_s


def log_problems(path: Path) -> tuple[int, int]:
    """(ERROR lines, WARN lines) of a node log (tracing's level column)."""
    errors = warnings = 0
    try:
        with open(path, errors="replace") as f:
            for line in f:
                if " ERROR " in line or "panicked" in line:
                    errors += 1
                elif " WARN " in line:
                    warnings += 1
    except FileNotFoundError:
        pass
    return errors, warnings


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


class Sampler:
    """Counts PatchArrays and their latency, keeps the latest statuses, and writes a CSV row per period."""

    def __init__(self, harness: pw.RosHarness, nodes: dict[str, int], logs: dict[str, Path], period: float, out: Path):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from patchwalk_msgs.msg import ExecutorStatus, MapperStatus, PatchArray
        from experiment import header_stamp_s

        self.header_stamp_s = header_stamp_s
        self.nodes, self.logs, self.period = nodes, logs, period
        self.lock = threading.Lock()
        self.maps = 0
        self.latencies: list[float] = []
        self.mapper_status = None
        self.executor_status = None
        self.faults: list[str] = []
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        node = harness.node
        with harness._lock:
            self.subs = [
                # Serialized: only the stamp is read, so the sampler costs no per-field Python objects.
                node.create_subscription(PatchArray, "/patch_mapper/patches", self._on_map, qos, raw=True),
                node.create_subscription(MapperStatus, "/patch_mapper/status", self._on_mapper, qos),
                node.create_subscription(ExecutorStatus, "/step_executor/status", self._on_executor, qos),
            ]
        self.rows: list[dict] = []
        self.csv_path = out / "soak.csv"
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="soak-sampler", daemon=True)

    def _on_map(self, raw: bytes) -> None:
        latency = time.time() - self.header_stamp_s(raw)
        with self.lock:
            self.maps += 1
            self.latencies.append(latency)

    def _on_mapper(self, msg) -> None:
        self.mapper_status = msg

    def _on_executor(self, msg) -> None:
        if msg.last_fault and (not self.faults or self.faults[-1] != msg.last_fault):
            self.faults.append(msg.last_fault)
        self.executor_status = msg

    def _run(self) -> None:
        start = time.monotonic()
        last_cpu = {name: proc_sample(pid)[1] for name, pid in self.nodes.items()}
        last_own_cpu = proc_sample(os.getpid())[1]
        fields = None
        with open(self.csv_path, "w", newline="") as f:
            writer = None
            next_at = start + self.period
            while not self.stop.wait(max(0.0, next_at - time.monotonic())):
                now = time.monotonic()
                elapsed = now - (next_at - self.period)
                next_at += self.period
                with self.lock:
                    maps, latencies = self.maps, self.latencies
                    self.maps, self.latencies = 0, []
                row = {"t_s": round(now - start, 1), "patch_arrays_per_s": round(maps / elapsed, 2),
                       "latency_p50_ms": round(1e3 * percentile(latencies, 0.5), 2),
                       "latency_p99_ms": round(1e3 * percentile(latencies, 0.99), 2)}
                for name, pid in self.nodes.items():
                    try:
                        rss, cpu = proc_sample(pid)
                    except (FileNotFoundError, ProcessLookupError):
                        rss, cpu = float("nan"), float("nan")
                    row[f"{name}_rss_mb"] = round(rss, 2)
                    row[f"{name}_cpu_pct"] = round(100.0 * (cpu - last_cpu[name]) / elapsed, 2)
                    last_cpu[name] = cpu
                    errors, warnings = log_problems(self.logs[name])
                    row[f"{name}_log_errors"] = errors
                    row[f"{name}_log_warnings"] = warnings
                own_cpu = proc_sample(os.getpid())[1]
                row["harness_cpu_pct"] = round(100.0 * (own_cpu - last_own_cpu) / elapsed, 2)
                last_own_cpu = own_cpu
                m = self.mapper_status
                row["mapper_frames_processed"] = m.frames_processed if m else 0
                row["mapper_frames_skipped"] = m.frames_skipped if m else 0
                row["mapper_frames_rejected"] = m.frames_rejected if m else 0
                row["executor_faults"] = len(self.faults)
                self.rows.append(row)
                if writer is None:
                    fields = list(row)
                    writer = csv.DictWriter(f, fieldnames=fields)
                    writer.writeheader()
                writer.writerow(row)
                f.flush()
                print(f"[soak {row['t_s']:7.0f} s] {row['patch_arrays_per_s']:5.1f} maps/s, latency p50 "
                      f"{row['latency_p50_ms']} ms p99 {row['latency_p99_ms']} ms, RSS "
                      + ", ".join(f"{n} {row[f'{n}_rss_mb']:.0f} MB" for n in self.nodes), flush=True)


def summarise(rows: list[dict], nodes: list[str], warmup_s: float, faults: list[str], trials: dict) -> dict:
    steady = [r for r in rows if r["t_s"] > warmup_s] or rows
    tenth = max(1, len(steady) // 10)
    first, last = steady[:tenth], steady[-tenth:]
    rate_first = statistics.mean(r["patch_arrays_per_s"] for r in first)
    rate_last = statistics.mean(r["patch_arrays_per_s"] for r in last)
    summary = {"samples": len(rows), "duration_s": rows[-1]["t_s"] if rows else 0, "warmup_s": warmup_s,
               "output_rate_first_per_s": round(rate_first, 2), "output_rate_last_per_s": round(rate_last, 2),
               "output_rate_drop_pct": round(100.0 * (rate_first - rate_last) / rate_first, 2) if rate_first else None,
               "latency_p50_ms_median": round(statistics.median(r["latency_p50_ms"] for r in steady), 2),
               "latency_p99_ms_max": round(max(r["latency_p99_ms"] for r in steady), 2),
               "executor_faults": faults, "trials": trials}
    for name in nodes:
        rss_first = statistics.mean(r[f"{name}_rss_mb"] for r in first)
        rss_last = statistics.mean(r[f"{name}_rss_mb"] for r in last)
        summary[f"{name}_rss_mb_after_warmup"] = round(rss_first, 1)
        summary[f"{name}_rss_mb_at_end"] = round(rss_last, 1)
        summary[f"{name}_rss_growth_pct"] = round(100.0 * (rss_last - rss_first) / rss_first, 2)
        summary[f"{name}_cpu_pct_mean"] = round(statistics.mean(r[f"{name}_cpu_pct"] for r in steady), 1)
        summary[f"{name}_log_errors"] = rows[-1][f"{name}_log_errors"]
    errors = sum(summary[f"{n}_log_errors"] for n in nodes) + len(faults)
    summary["goals"] = {
        "output_rate_drop_le_1_pct": summary["output_rate_drop_pct"] is not None and summary["output_rate_drop_pct"] <= 1.0,
        "rss_growth_lt_5_pct": all(summary[f"{n}_rss_growth_pct"] < 5.0 for n in nodes),
        "no_error": errors == 0,
    }
    return summary


def plot(rows: list[dict], nodes: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["t_s"] / 60.0 for r in rows]
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    for name in nodes:
        axes[0].plot(t, [r[f"{name}_rss_mb"] for r in rows], label=name)
        axes[1].plot(t, [r[f"{name}_cpu_pct"] for r in rows], label=name)
    axes[2].plot(t, [r["patch_arrays_per_s"] for r in rows])
    axes[3].plot(t, [r["latency_p50_ms"] for r in rows], label="p50")
    axes[3].plot(t, [r["latency_p99_ms"] for r in rows], label="p99")
    for ax, label in zip(axes, ("RSS [MB]", "CPU [%]", "PatchArray [1/s]", "latency [ms]")):
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[3].legend(fontsize=7)
    axes[3].set_xlabel("time [min]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="run time after training (default 60)")
    parser.add_argument("--period", type=float, default=10.0, help="s between samples (default 10)")
    parser.add_argument("--warmup", type=float, default=120.0, help="s of the run left out of the growth figures")
    parser.add_argument("--out", type=Path, default=REPO / "build" / "soak")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    env = pw.ros_environment(args.out)
    os.environ.update(env)

    import experiment as ex

    # Ctrl-C / SIGTERM end the run after the current trial; the summary is still written.
    stop_requested = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop_requested.set())
    processes: dict[str, pw.NodeProcess] = {}
    bus_log = open(args.out / "sim_bus.log", "w")
    bus = subprocess.Popen([str(pw.binary("step_executor")), "sim-bus"], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=bus_log, text=True, cwd=REPO)
    harness = pw.RosHarness("soak")
    sampler = None
    experiment = None
    aborted: str | None = None  # why the trial loop ended early, if it did
    trials = {"correct": 0, "wrong": 0, "no_match": 0, "untrained_no_execution": 0, "executed_untrained": 0}
    try:
        pty = (bus.stdout.readline() if bus.stdout else "").strip()
        if not pty.startswith("/dev/"):
            raise RuntimeError(f"sim-bus printed {pty!r} (log: {args.out / 'sim_bus.log'})")
        processes["terrain_sim"] = pw.NodeProcess("terrain_sim", ["run"], env, args.out)
        harness.wait_for_nodes("/terrain_sim", timeout=60)
        processes["patch_mapper"] = pw.NodeProcess("patch_mapper", ["run", "--config", str(ex.SIM_MAPPER_CONFIG)], env, args.out)
        harness.wait_for_nodes("/patch_mapper", timeout=60)
        processes["step_executor"] = pw.NodeProcess(
            "step_executor", ["run", "--param", f"bus.port={pty}", *ex.SIM_BUS_PARAMS,
                              "--param", f"library_path={args.out / 'motions.yaml'}", "--param", "ros.status_rate_hz=20"],
            env, args.out)
        harness.wait_for_nodes("/terrain_sim", "/patch_mapper", "/step_executor", timeout=60)
        rocks = ex.load_scene([])
        config = ex.ExperimentConfig(out_dir=args.out / "experiment")
        experiment = ex.Experiment(harness, ex.Hand(bus.stdin), rocks, config)
        experiment.status.wait(lambda _: True, 60, "/step_executor/status")
        trained = [r for r in rocks if r.trained]
        motion_of = {rock.index: experiment.train(rock) for rock in trained}
        pids = {name: p.proc.pid for name, p in processes.items()}
        sampler = Sampler(harness, pids, {n: p.log_path for n, p in processes.items()}, args.period, args.out)
        sampler.thread.start()
        end = time.monotonic() + 60.0 * args.minutes
        order = [*trained, *[r for r in rocks if not r.trained]]
        i = 0
        try:
            while time.monotonic() < end and not stop_requested.is_set():
                if not all(p.alive() for p in processes.values()):
                    dead = [n for n, p in processes.items() if not p.alive()]
                    raise RuntimeError(f"node(s) exited during the soak: {dead}")
                rock = order[i % len(order)]
                i += 1
                expected = motion_of.get(rock.index) if rock.trained else None
                trial = experiment.trial(rock, expected)
                if rock.trained:
                    key = {"correct": "correct", "wrong": "wrong"}.get(trial.outcome, "no_match")
                    trials[key] += 1
                else:
                    trials["executed_untrained" if trial.played else "untrained_no_execution"] += 1
            experiment.arm(False)
        except (RuntimeError, TimeoutError) as e:
            # What was sampled up to here is still summarised; the run counts as failed.
            aborted = f"{type(e).__name__}: {e}"
            print(f"soak: aborted after {sampler.rows[-1]['t_s'] if sampler.rows else 0:.0f} s: {aborted}", file=sys.stderr)
    finally:
        if sampler is not None:
            sampler.stop.set()
            sampler.thread.join(timeout=30)
        if experiment is not None:
            experiment.close()
        for name in ("step_executor", "patch_mapper", "terrain_sim"):
            if name in processes:
                try:
                    processes[name].stop()
                except AssertionError as e:
                    print(f"soak: {e}", file=sys.stderr)
        bus.terminate()
        bus.wait(timeout=30)
        bus_log.close()
        harness.shutdown()
    if sampler is None or not sampler.rows:
        print("soak: no samples taken", file=sys.stderr)
        return 1
    nodes = list(sampler.nodes)
    summary = summarise(sampler.rows, nodes, args.warmup, sampler.faults, trials)
    summary["aborted"] = aborted
    summary["goals"]["ran_to_the_end"] = aborted is None
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    plot(sampler.rows, nodes, args.out / "soak.png")
    print(json.dumps(summary, indent=2))
    print(f"csv: {sampler.csv_path}\nplot: {args.out / 'soak.png'}")
    return 0 if all(summary["goals"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
