"""The import packages depend on each other one way: perception <- driver <- bringup (<- bench).

Every `import` and `from ... import` in the three packages and in bench/ is read (including lazy
ones inside functions), and an edge that points up the stack fails, as does a ROS or bag library
imported below `touchroller_bringup`.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("touchroller_perception", "touchroller_driver", "touchroller_bringup", "bench")
#: Libraries that only the ROS layer may import: rclpy and launch, ROS messages, and recordings.
ROS_ONLY = ("rclpy", "launch", "launch_ros", "rosbags", "rosidl_runtime_py", "builtin_interfaces")
ROS_ONLY_SUFFIXES = ("_msgs", "_srvs", "_interfaces")


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, top-level module) of every absolute import in a file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module.split(".")[0]))
    return found


def violations(package: str, root: Path = ROOT) -> list[str]:
    rank = LAYERS.index(package)
    bad = []
    for path in sorted((root / package).rglob("*.py")):
        for line, module in imports(path):
            where = f"{path.relative_to(root)}:{line} imports {module}"
            if module in LAYERS and LAYERS.index(module) > rank:
                bad.append(where)
            elif rank < LAYERS.index("touchroller_bringup") and (
                    module in ROS_ONLY or module.endswith(ROS_ONLY_SUFFIXES)):
                bad.append(where + " (ROS only in touchroller_bringup)")
    return bad


@pytest.mark.parametrize("package", LAYERS)
def test_no_import_points_up_the_stack(package):
    assert violations(package) == []


def test_the_check_sees_an_upward_import(tmp_path):
    fake = tmp_path / "touchroller_perception"
    fake.mkdir()
    (fake / "bad.py").write_text("def f():\n    from touchroller_driver.sim import load_scene\n    import rclpy\n")
    assert violations("touchroller_perception", tmp_path) == [
        "touchroller_perception/bad.py:2 imports touchroller_driver",
        "touchroller_perception/bad.py:3 imports rclpy (ROS only in touchroller_bringup)"]
