"""The README's topic and service table and the names the nodes use (the `pub const ...: &str = "/..."`
constants of their `src/ros/` modules) are the same set, so the table cannot drift from the code."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def names_in_code() -> set[str]:
    names = set()
    for path in (ROOT / "nodes").rglob("*.rs"):
        if "third_party" in path.parts:
            continue
        names.update(re.findall(r'pub const [A-Z_]+: &str = "(/[a-z_/]+)";', path.read_text()))
    return names


def names_in_readme() -> set[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Topics and services", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"^\| `(/[a-z_/]+)` \|", section, flags=re.M))


def test_readme_table_lists_exactly_the_names_of_the_code():
    code, readme = names_in_code(), names_in_readme()
    assert code, "no names found in the nodes' ros modules"
    assert readme == code, f"only in the README: {sorted(readme - code)}; only in the code: {sorted(code - readme)}"
