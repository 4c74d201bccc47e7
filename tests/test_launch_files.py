"""The launch files (XML launch format, installed in step_executor's share) checked without launch_ros:
their substitutions resolve against the colcon install, every <node pkg exec> is an executable of the
install (or a ROS package step_executor's package.xml declares), every parameters file passed loads
through the node's `--ros-args --params-file` (the command line launch_ros builds) and brings the node
up, and every remap's `from` is a topic the node really has on the graph."""

from __future__ import annotations

import re
import shlex
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

import colcon_install as ci
import patchwalk_testing as pw
from conftest import ENV

LAUNCH_PACKAGE = "step_executor"
LAUNCH_FILES = ("robot.launch.xml", "simulation.launch.xml")
# The launch arguments each file must offer (README "ROS 2 workspace").
REQUIRED_ARGS = {
    "robot.launch.xml": {"use_sim_time", "depth_topic", "camera_info_topic", "imu_topic", "rviz"},
    "simulation.launch.xml": {"use_sim_time", "rock", "rviz"},
}
# The processes each file starts (package, executable, first argument).
REQUIRED_NODES = {
    "robot.launch.xml": {("patch_mapper", "patch_mapper", "run"), ("step_executor", "step_executor", "run"),
                         ("robot_state_publisher", "robot_state_publisher", ""), ("rviz2", "rviz2", "-d")},
    "simulation.launch.xml": {("terrain_sim", "terrain_sim", "run"), ("step_executor", "step_executor", "sim-bus"),
                              ("patch_mapper", "patch_mapper", "run"), ("step_executor", "step_executor", "run"),
                              ("robot_state_publisher", "robot_state_publisher", "")},
}

_SUBSTITUTION = re.compile(r"\$\((find-pkg-share|var|command)\s+([^()$]*)\)")


@dataclass
class LaunchNode:
    package: str
    executable: str
    name: str
    args: list[str]
    params_files: list[Path] = field(default_factory=list)
    params: dict[str, object] = field(default_factory=dict)
    remaps: list[tuple[str, str]] = field(default_factory=list)


class LaunchFile:
    """One XML launch file with its <arg> defaults applied to every substitution."""

    def __init__(self, path: Path):
        self.path = path
        self.root = ET.parse(path).getroot()
        assert self.root.tag == "launch", f"{path}: root element <{self.root.tag}>"
        self.args: dict[str, str] = {}
        for arg in self.root.iter("arg"):
            assert "default" in arg.attrib, f"{path}: <arg name={arg.get('name')!r}> has no default"
            self.args[arg.attrib["name"]] = self.substitute(arg.attrib["default"])

    def substitute(self, text: str) -> str:
        """Resolve $(find-pkg-share P), $(var A) and $(command 'cat F') innermost first."""
        while (match := _SUBSTITUTION.search(text)) is not None:
            kind, value = match.group(1), match.group(2).strip()
            if kind == "find-pkg-share":
                result = str(ci.package_share(value))
            elif kind == "var":
                assert value in self.args, f"{self.path}: $(var {value}) names no <arg> declared before it"
                result = self.args[value]
            else:
                words = shlex.split(shlex.split(value)[0]) if value.startswith("'") else shlex.split(value)
                assert words[0] == "cat" and len(words) == 2, f"{self.path}: unexpected $(command {value})"
                result = Path(words[1]).read_text()
            text = text[:match.start()] + result + text[match.end():]
        assert "$(" not in text, f"{self.path}: unresolved substitution in {text!r}"
        return text

    def nodes(self) -> list[LaunchNode]:
        nodes = []
        for node in self.root.iter("node"):
            launch_node = LaunchNode(package=node.attrib["pkg"], executable=node.attrib["exec"], name=node.attrib["name"],
                                     args=shlex.split(self.substitute(node.get("args", ""))))
            for param in node.findall("param"):
                if "from" in param.attrib:
                    launch_node.params_files.append(Path(self.substitute(param.attrib["from"])))
                else:
                    launch_node.params[param.attrib["name"]] = _yaml_value(self.substitute(param.attrib["value"]))
            for remap in node.findall("remap"):
                launch_node.remaps.append((self.substitute(remap.attrib["from"]), self.substitute(remap.attrib["to"])))
            nodes.append(launch_node)
        return nodes


def _yaml_value(text: str) -> object:
    """A launch <param value> as launch_ros types it (YAML rules: bool, int, float, else string)."""
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:  # e.g. a URDF
        return text
    return value if isinstance(value, (bool, int, float)) else text


def _launch_file(name: str) -> LaunchFile:
    return LaunchFile(ci.package_share(LAUNCH_PACKAGE) / "launch" / name)


def _declared_exec_depends() -> set[str]:
    manifest = ET.parse(ci.package_share(LAUNCH_PACKAGE) / "package.xml").getroot()
    return {e.text for e in manifest.iter() if e.tag in ("exec_depend", "depend")}


def _patchwalk_nodes() -> list[tuple[str, LaunchNode]]:
    return [(f, n) for f in LAUNCH_FILES for n in _launch_file(f).nodes() if n.package in ci.NODE_PACKAGES]


@pytest.mark.parametrize("name", LAUNCH_FILES)
def test_launch_file_resolves_and_starts_executables_of_the_install(name):
    launch = _launch_file(name)
    assert REQUIRED_ARGS[name] <= set(launch.args), f"{name}: missing launch arguments {REQUIRED_ARGS[name] - set(launch.args)}"
    nodes = launch.nodes()
    started = {(n.package, n.executable, n.args[0] if n.args else "") for n in nodes}
    assert REQUIRED_NODES[name] <= started, f"{name}: missing {REQUIRED_NODES[name] - started}"
    assert len({n.name for n in nodes}) == len(nodes), f"{name}: two nodes with one name"
    external = _declared_exec_depends()
    for node in nodes:
        if node.package in ci.NODE_PACKAGES:
            ci.executable(node.package, node.executable)
        else:
            assert node.package in external, f"{name}: {node.package} is neither in the install nor an exec_depend"
        for params_file in node.params_files:
            assert params_file.is_file(), f"{name}: {node.name}'s parameters file {params_file} does not exist"
            assert params_file.is_relative_to(ci.INSTALL), f"{name}: {params_file} is not from the install"
        if node.package == "rviz2":
            rviz_config = Path(node.args[node.args.index("-d") + 1])
            assert rviz_config == ci.package_share(LAUNCH_PACKAGE) / "config" / "patchwalk.rviz" and rviz_config.is_file()
        if node.package == "robot_state_publisher":
            description = ET.fromstring(str(node.params["robot_description"]))
            assert description.tag == "robot" and description.get("name"), "robot_description is not a URDF"


def _started(ros, log_dir, tmp_path, node: LaunchNode, ros_args: list[str]) -> pw.NodeProcess:
    env = {**ci.sourced_environment(), **ENV}
    cwd = tmp_path / node.name
    cwd.mkdir(exist_ok=True)
    return pw.NodeProcess(node.name, [*node.args, *ros_args], env, log_dir, executable=ci.executable(node.package, node.executable),
                          cwd=cwd)


def _topics_of(ros, node_name: str, timeout: float = pw.DEFAULT_TIMEOUT_S) -> set[str]:
    """Topics the node subscribes or publishes, from the graph (waits until it shows some)."""
    deadline = time.monotonic() + timeout
    while True:
        topics = {t for t, _ in ros.node.get_subscriber_names_and_types_by_node(node_name, "/")}
        topics |= {t for t, _ in ros.node.get_publisher_names_and_types_by_node(node_name, "/")}
        if topics or time.monotonic() > deadline:
            return topics
        time.sleep(0.1)


@pytest.mark.parametrize("launch_name, node", [pytest.param(f, n, id=f"{f}:{n.name}") for f, n in _patchwalk_nodes() if n.remaps]
                         if ci.INSTALL.joinpath("setup.bash").is_file() else [])
def test_remaps_name_topics_the_node_has(ros, log_dir, tmp_path, launch_name, node):
    process = _started(ros, log_dir, tmp_path, node, [])
    try:
        ros.wait_for_nodes("/" + node.executable)
        topics = _topics_of(ros, node.executable)
        unknown = [src for src, _ in node.remaps if src not in topics]
        assert not unknown, f"{launch_name}: {node.name} has no topics {unknown} (its topics: {sorted(topics)})"
    finally:
        process.stop()


def _params_cases():
    if not ci.INSTALL.joinpath("setup.bash").is_file():
        return []
    return [pytest.param(f, n, id=f"{f}:{n.name}") for f, n in _patchwalk_nodes() if n.args and n.args[0] == "run"]


@pytest.mark.parametrize("launch_name, node", _params_cases())
def test_node_comes_up_with_the_ros_args_launch_ros_passes(ros, log_dir, tmp_path, launch_name, node):
    """`<exe> <args> --ros-args -r __node:=N --params-file F... -r from:=to`, as launch_ros builds it (the
    <param name value> pairs in a '/**' parameters file of their own)."""
    import yaml

    ros_args = ["--ros-args", "-r", f"__node:={node.name}"]
    for params_file in node.params_files:
        ros_args += ["--params-file", str(params_file)]
    if node.params:
        inline = tmp_path / f"launch_params_{node.name}.yaml"
        inline.write_text(yaml.safe_dump({"/**": {"ros__parameters": node.params}}))
        ros_args += ["--params-file", str(inline)]
    for src, dst in node.remaps:
        ros_args += ["-r", f"{src}:={dst}"]
    process = _started(ros, log_dir, tmp_path, node, ros_args)
    try:
        pw.wait_until(lambda: not process.alive() or "/" + node.name in ros.node_names(), f"{node.name} on the graph")
        assert process.alive(), f"{node.name} exited with {process.proc.returncode}:\n{process.log()}"
        topics = _topics_of(ros, node.name)
        for _, dst in node.remaps:
            assert dst in topics, f"{node.name}: remapped topic {dst} not on the graph ({sorted(topics)})"
    finally:
        if process.alive():
            process.stop()
