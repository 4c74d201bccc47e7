"""The colcon install of the repository (`launch_scripts/test.sh` builds it into build/colcon/install):
where it is, the environment `source install/setup.bash` gives, and the ament index lookups `ros2 run`
and `ros2 launch` make in it (share directory, `lib/<package>/<executable>`).

PATCHWALK_COLCON_INSTALL names another install directory.
"""

from __future__ import annotations

import functools
import os
import subprocess
from pathlib import Path

import patchwalk_testing as pw

INSTALL = Path(os.environ.get("PATCHWALK_COLCON_INSTALL", pw.REPO / "build" / "colcon" / "install"))

# The colcon packages of the repository: the interface package and the three node packages.
NODE_PACKAGES = ("patch_mapper", "step_executor", "terrain_sim")
PACKAGES = ("patchwalk_msgs", *NODE_PACKAGES)


def require_install() -> Path:
    setup = INSTALL / "setup.bash"
    assert setup.is_file(), (f"{setup} missing: build the colcon install first (launch_scripts/test.sh does, "
                             "or see the README's \"ROS 2 workspace\" section)")
    return INSTALL


@functools.lru_cache(maxsize=1)
def sourced_environment() -> dict[str, str]:
    """os.environ after `source install/setup.bash` in bash (what a user's shell has)."""
    setup = require_install() / "setup.bash"
    out = subprocess.run(["bash", "-c", f'source "{setup}" && env -0'], capture_output=True, check=True, timeout=60,
                         env=dict(os.environ)).stdout
    env = {}
    for entry in out.split(b"\0"):
        key, sep, value = entry.decode(errors="replace").partition("=")
        if sep:
            env[key] = value
    return env


def prefixes() -> list[Path]:
    return [Path(p) for p in sourced_environment().get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]


def package_prefix(package: str) -> Path:
    """The first prefix of AMENT_PREFIX_PATH whose ament index registers `package` (ament_index_python's
    get_package_prefix)."""
    for prefix in prefixes():
        if (prefix / "share" / "ament_index" / "resource_index" / "packages" / package).is_file():
            return prefix
    raise AssertionError(f"package {package!r} not in the ament index of AMENT_PREFIX_PATH {prefixes()}")


def package_share(package: str) -> Path:
    """`$(find-pkg-share package)`."""
    return package_prefix(package) / "share" / package


def executable(package: str, name: str) -> Path:
    """What `ros2 run package name` starts: `<prefix>/lib/<package>/<name>`, executable."""
    path = package_prefix(package) / "lib" / package / name
    assert path.is_file() and os.access(path, os.X_OK), f"`ros2 run {package} {name}` would not find {path}"
    return path
