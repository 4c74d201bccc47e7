"""`patch_mapper footholds plan` on a terrain_sim rock scene (the CNN IV coarse route planner over the
patch pipeline's valid patches): a route to a goal ahead of the robot is written as JSON (stances with
left/right sole positions) and a PNG; a goal off the terrain, an empty hold file and a hold file that
is not a list of holds end with a clear error, never a panic."""

import json
import struct
import subprocess
from pathlib import Path

import pytest

import patchwalk_testing as pw

SIM_CONFIG = str(pw.REPO / "config" / "patch_mapper_sim.yaml")
# The fused map of the robot's birds-eye view covers a strip 0.18-0.25 m ahead of the camera: the
# goal lies on its left end, the start defaults to the bottom centre of the image.
GOAL = "0.22,0.15"
GOAL_XY = (0.22, 0.15)


@pytest.fixture(scope="module")
def rock_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rock_scene") / "rock0"
    subprocess.run([str(pw.binary("terrain_sim")), "record", str(out), "--rock", "0", "--frames", "10"],
                   check=True, capture_output=True, text=True, timeout=300)
    return out


def plan(dataset: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [str(pw.binary("patch_mapper")), "footholds", "plan", str(dataset), "--out", str(out), "--config", SIM_CONFIG, *args],
        capture_output=True, text=True, timeout=600,
    )
    assert "panicked" not in result.stderr, result.stderr
    return result


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_a_route_over_the_rock_scene_is_written(rock_scene, tmp_path):
    out = tmp_path / "plan"
    result = plan(rock_scene, out, "--goal", GOAL)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "plan time" in result.stdout
    route = json.loads((out / "route.json").read_text())
    assert route["frame_id"].startswith("heading")
    assert route["stats"]["clusters"] <= 30 and route["stats"]["holds_in"] > 0
    stances = route["stances"]
    assert len(stances) >= 2
    for s in stances:
        assert len(s["left"]) == 3 and len(s["right"]) == 3
        assert 0.0 < s["flex"] <= 1.0
        # The soles are apart and within two legs' reach of each other.
        gap = sum((a - b) ** 2 for a, b in zip(s["left"], s["right"])) ** 0.5
        assert 0.06 <= gap <= 0.5, s
    # Costs grow along the route and the body path ends near the goal.
    assert [s["cost"] for s in stances] == sorted(s["cost"] for s in stances)
    end = route["body_path"][-1]
    assert ((end[0] - GOAL_XY[0]) ** 2 + (end[1] - GOAL_XY[1]) ** 2) ** 0.5 <= route["planner"]["snap_m"] + 1e-9, end
    assert route["length_m"] > 0.05
    assert png_size(out / "route.png") == (640, 480)
    holds = json.loads((out / "holds.json").read_text())
    assert len(holds) == route["stats"]["holds_in"]


def test_the_holds_file_is_an_input_too(rock_scene, tmp_path):
    first = tmp_path / "first"
    assert plan(rock_scene, first, "--goal", GOAL).returncode == 0
    again = tmp_path / "again"
    result = plan(rock_scene, again, "--goal", GOAL, "--holds", str(first / "holds.json"))
    assert result.returncode == 0, result.stderr
    a = json.loads((first / "route.json").read_text())
    b = json.loads((again / "route.json").read_text())
    assert b["holds_source"].startswith("file")
    assert b["stats"]["holds_in"] == a["stats"]["holds_in"]
    assert len(b["stances"]) >= 2


def test_bad_goals_and_holds_are_clear_errors(rock_scene, tmp_path):
    result = plan(rock_scene, tmp_path / "far", "--goal", "10,0")
    assert result.returncode == 1
    assert "outside the observed terrain" in result.stderr, result.stderr
    empty = tmp_path / "empty.json"
    empty.write_text("[]")
    result = plan(rock_scene, tmp_path / "empty", "--goal", GOAL, "--holds", str(empty))
    assert result.returncode == 1 and "hold set is empty" in result.stderr, result.stderr
    broken = tmp_path / "broken.json"
    broken.write_text('[{"position": [0.5, 0.0], "score": 1.0}]')
    result = plan(rock_scene, tmp_path / "broken", "--goal", GOAL, "--holds", str(broken))
    assert result.returncode == 1 and "not a list of holds" in result.stderr, result.stderr
    result = plan(rock_scene, tmp_path / "nan", "--goal", "nan,0")
    assert result.returncode == 2 and "finite" in result.stderr, result.stderr
