"""The colcon install (build/colcon/install, built by launch_scripts/test.sh): every package is in the
ament index, the executables are where `ros2 run` looks, the share directories hold config, URDF and
launch files, and a node started from the install, outside the repository, comes up on the graph,
answers a service and loads its URDF from its share directory through the ament index."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest
from patchwalk_msgs.srv import ListMotions

import colcon_install as ci
import patchwalk_testing as pw
from conftest import ENV

EXECUTABLES = {"patch_mapper": "patch_mapper", "step_executor": "step_executor", "terrain_sim": "terrain_sim"}
SHARE_FILES = {
    "patch_mapper": ["config/patch_mapper.yaml", "config/patch_mapper_sim.yaml", "package.xml"],
    "step_executor": ["config/step_executor.yaml", "config/patchwalk.rviz", "urdf/rpbp.urdf",
                      "launch/robot.launch.xml", "launch/simulation.launch.xml", "package.xml"],
    "terrain_sim": ["config/terrain_sim.yaml", "urdf/rpbp.urdf", "package.xml"],
}


def test_every_crate_is_a_colcon_package_or_ignored():
    """`colcon build` of a workspace around the repository crawls every directory: a crate without a
    package.xml would be taken for a plain cargo package (colcon-cargo) and built and installed on its
    own. Library crates are built as the nodes' dependencies and carry a COLCON_IGNORE."""
    packages, stray = set(), []
    for manifest in sorted(pw.REPO.glob("nodes/**/Cargo.toml")) + [pw.REPO / "msgs" / "Cargo.toml"]:
        crate = manifest.parent
        ignored = any((d / "COLCON_IGNORE").exists() for d in [crate, *crate.parents] if d.is_relative_to(pw.REPO))
        if (crate / "package.xml").is_file():
            assert not ignored, f"{crate} has a package.xml but is under a COLCON_IGNORE"
            packages.add(ET.parse(crate / "package.xml").getroot().findtext("name"))
        elif not ignored:
            stray.append(str(crate.relative_to(pw.REPO)))
    assert not stray, f"crates neither colcon packages (package.xml) nor under a COLCON_IGNORE: {stray}"
    assert packages == set(ci.PACKAGES)


@pytest.mark.parametrize("package", ci.PACKAGES)
def test_package_is_in_the_ament_index_of_the_sourced_install(package):
    prefix = ci.package_prefix(package)
    assert prefix == ci.INSTALL / package, f"{package} found in {prefix}, not in the colcon install"
    manifest = ET.parse(ci.package_share(package) / "package.xml").getroot()
    assert manifest.findtext("name") == package


@pytest.mark.parametrize("package", ci.NODE_PACKAGES)
def test_executable_and_share_files_are_where_ros2_finds_them(package):
    ci.executable(package, EXECUTABLES[package])
    share = ci.package_share(package)
    missing = [f for f in SHARE_FILES[package] if not (share / f).is_file()]
    assert not missing, f"{share} lacks {missing}"
    # Installed copies of the repository's files, not stale ones.
    for rel in SHARE_FILES[package]:
        source = (pw.REPO / rel) if not rel.startswith("launch/") else (pw.REPO / "nodes/execution/step_executor" / rel)
        if rel != "package.xml":
            assert (share / rel).read_bytes() == source.read_bytes(), f"{share / rel} differs from {source}"


def test_installed_step_executor_runs_outside_the_repository_with_its_share_urdf(ros, log_dir, tmp_path):
    """`ros2 run step_executor step_executor run` from a directory outside the repository, in the sourced
    environment: on the graph, list_motions answers, and the URDF came from the package share."""
    env = {**ci.sourced_environment(), **ENV}
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    node = pw.NodeProcess("step_executor", ["run", "--param", f"library_path={outside / 'motions.yaml'}"], env, log_dir,
                          executable=ci.executable("step_executor", "step_executor"), cwd=outside)
    try:
        ros.wait_for_nodes("/step_executor")
        response = ros.call(ListMotions, "/step_executor/list_motions")
        assert list(response.motions) == []
        share_urdf = ci.package_share("step_executor") / "urdf" / "rpbp.urdf"
        pw.wait_until(lambda: "robot model" in node.log(), "the robot model log line")
        line = next(line for line in node.log().splitlines() if "robot model" in line)
        assert f"robot model {share_urdf} (package share (ament index))" in line, line
        assert str(pw.REPO / "urdf") not in line, "loaded the repository's URDF, not the installed one"
    finally:
        node.stop()
