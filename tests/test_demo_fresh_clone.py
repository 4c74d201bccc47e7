"""Command 1 on a fresh machine: `launch_scripts/demo.sh` in a fresh clone of this repository's HEAD, without
a venv, creates the venv with the pinned ROS 2 Jazzy wheels and patchwalk_msgs (launch_scripts/setup.sh),
starts the system and runs the four-rock experiment with 1 trial per rock.

What is tested is the HEAD commit: uncommitted changes of the working tree are not in the clone (commit
first). The Rust build is shared through CARGO_TARGET_DIR (this run's target directory): each file of the
clone gets the time of the last commit that changed it as its modification time, so cargo reuses the
current build where it is newer than those changes and rebuilds what changed since. Uncommitted Rust changes already built into that target
directory are therefore in the binaries. The venv is never shared: the clone gets its own `.venv` from
PyPI (about 1.5 min here, downloads included).

Parallel-safe: its own clone and venv in the test's tmp dir, the ROS domain of this pytest worker, DDS on
loopback (demo.sh's environment). Deselect with `-m "not fresh_clone"`.
"""

from __future__ import annotations

import os
import re
import subprocess
import time

import pytest

import patchwalk_testing as pw

pytestmark = pytest.mark.fresh_clone


def git(*args: str, cwd=pw.REPO) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def test_demo_sets_up_and_runs_the_experiment_in_a_fresh_clone(tmp_path):
    head = git("rev-parse", "HEAD")
    clone = tmp_path / "patchwalk"
    git("clone", "--quiet", "--no-checkout", str(pw.REPO), str(clone), cwd=tmp_path)
    git("checkout", "--quiet", "--detach", head, cwd=clone)
    # Each file's modification time: the time of the last commit that changed it.
    changed_at: dict[str, int] = {}
    when = 0
    for line in git("log", "--format=@%ct", "--name-only", cwd=clone).splitlines():
        if line.startswith("@"):
            when = int(line[1:])
        elif line:
            changed_at.setdefault(line, when)
    for name in git("ls-files", "-z", cwd=clone).split("\0"):
        if name and (clone / name).is_file() and name in changed_at:
            os.utime(clone / name, (changed_at[name], changed_at[name]))
    assert not (clone / ".venv").exists()

    env = {k: v for k, v in os.environ.items() if k not in ("PATCHWALK_VENV", "VIRTUAL_ENV", "PYTHONPATH")}
    env.update(CARGO_TARGET_DIR=str(pw.TARGET_DIR.parent), DEMO_TRIALS="1", DEMO_UNTRAINED_TRIALS="1",
               CARGO_TERM_COLOR="never")
    log_path = tmp_path / "demo.log"
    started = time.monotonic()
    with open(log_path, "w") as log:
        demo = subprocess.run([str(clone / "launch_scripts" / "demo.sh")], cwd=clone, env=env, stdin=subprocess.DEVNULL,
                              stdout=log, stderr=subprocess.STDOUT, timeout=900)
    seconds = time.monotonic() - started
    output = log_path.read_text()
    tail = f"demo.sh after {seconds:.0f} s, exit {demo.returncode}; last lines:\n" + "\n".join(output.splitlines()[-40:])

    # Each step announced, the venv created in the clone and used by the experiment.
    for step in ("=== [1/4] setup", "=== [2/4] building", "=== [3/4] starting", "=== [4/4] experiment"):
        assert step in output, tail
    assert "[setup] === venv " + str(clone / ".venv") in output, tail
    assert "skipped the experiment" not in output, tail
    python = clone / ".venv" / "bin" / "python"
    subprocess.run([str(python), "-c", "import rclpy, patchwalk_msgs.msg, matplotlib"], check=True)

    # The table: every rock once, nothing wrong, nothing executed in front of an untrained rock. A
    # trained rock's single trial may end without a match (stochastic maps): at most one of four.
    assert "=== experiment table" in output, tail
    rows = re.findall(r"^(rock \d|untrained \d)\s+(yes|no)\s+(\d+)\s+(\d+|-)\s+(\d+)\s+(\d+)$", output, re.M)
    assert len(rows) == 8, tail
    trained = [r for r in rows if r[1] == "yes"]
    assert all(r[2] == "1" and r[4] == "0" for r in rows), tail
    assert sum(int(r[3]) for r in trained) >= 3, tail
    assert all(r[5] == "1" for r in rows if r[1] == "no"), tail
    pictures = clone / "build" / "demo" / "experiment"
    assert (pictures / "servo_trajectories.png").exists() and list(pictures.glob("patch_map_rock_*.png")), tail
    for name in ("step_executor", "patch_mapper", "terrain_sim", "sim_bus"):
        assert f"{name}: stopped cleanly" in output, tail
    # demo.sh exits non-zero when a trained rock had a trial without a match; the asserts above allow one.
    assert demo.returncode in (0, 1), tail
    print(f"fresh clone: demo.sh took {seconds:.0f} s")
