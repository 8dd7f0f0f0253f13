"""interfaces/: the interface packages built where no wheel has them (tf2_msgs, ur_dashboard_msgs) and our own
touchroller_interfaces, which exists nowhere else: colcon must find it in a workspace (README "With ROS 2"),
its manifest must be valid, and the built action must be the one the sweep node fills in."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
INTERFACES = ROOT / "interfaces" / "touchroller_interfaces"


def _readme_colcon_build() -> list[str]:
    """The arguments of the README's `colcon build` in the workspace."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    found = re.search(r"^cd ~/tr_ws && colcon build(.*)$", readme, re.MULTILINE)
    assert found, "README: no `cd ~/tr_ws && colcon build ...` line"
    return shlex.split(found.group(1).split("#")[0])


def _discover(workspace: Path, argv: list[str]) -> dict[str, str]:
    """What colcon finds from `workspace` with these arguments (what `colcon list` runs), name -> type."""
    import argparse
    import os

    discovery = pytest.importorskip("colcon_core.package_discovery", reason="colcon is not installed")
    from colcon_core.package_identification import get_package_identification_extensions

    parser = argparse.ArgumentParser()
    discovery.add_package_discovery_arguments(parser)
    args, _ = parser.parse_known_args(argv)
    here = os.getcwd()
    os.chdir(workspace)
    try:
        found = discovery.discover_packages(args, get_package_identification_extensions())
    finally:
        os.chdir(here)
    return {package.name: package.type for package in found}


@pytest.fixture
def workspace(tmp_path: Path) -> Path:
    """~/tr_ws with the clone in src/touchroller_bringup (a link to this checkout)."""
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "touchroller_bringup").symlink_to(ROOT, target_is_directory=True)
    return tmp_path


def test_the_readmes_colcon_build_finds_both_packages(workspace: Path):
    found = _discover(workspace, _readme_colcon_build())
    assert found.get("touchroller_bringup") == "ros.ament_python"
    assert found.get("touchroller_interfaces") == "ros.ament_cmake"
    assert not {"tf2_msgs", "ur_dashboard_msgs"} & set(found)   # a ROS install has those (COLCON_IGNORE)


def test_a_plain_colcon_build_finds_the_package_only(workspace: Path):
    """Why the README names the path: colcon does not look inside a package for more packages."""
    assert set(_discover(workspace, [])) == {"touchroller_bringup"}


def test_the_interface_manifest_is_valid_and_named_by_the_package():
    from catkin_pkg.package import parse_package

    package = parse_package(INTERFACES / "package.xml")
    package.validate()
    assert package.name == "touchroller_interfaces" and package.get_build_type() == "ament_cmake"
    assert "rosidl_interface_packages" in {group.name for group in package.member_of_groups}
    assert "action_msgs" in {d.name for d in package.build_depends}   # rosidl needs it for an action
    assert "touchroller_interfaces" in {d.name for d in parse_package(ROOT / "package.xml").exec_depends}


def test_the_built_action_has_what_the_sweep_node_fills_in():
    sweep = pytest.importorskip("touchroller_interfaces.action", reason="touchroller_interfaces is not built").Sweep
    from touchroller_bringup.sweep_action import ARRAY_FIELDS, SCALAR_FIELDS, Outcome

    goal = sweep.Goal()
    for name in SCALAR_FIELDS:
        assert getattr(goal, name) < 0.0, name   # unset: the node's parameter
    for name in ARRAY_FIELDS:
        assert len(getattr(goal, name)) == 0, name
    assert {o.name: o.value for o in Outcome} == {name: getattr(sweep.Result, name) for name in Outcome.__members__}
    assert {"pass_index", "pass_count", "coverage", "distance", "phase"} <= set(
        sweep.Feedback.get_fields_and_field_types())
    assert {"outcome", "message", "passes_done", "pass_count", "distance"} <= set(
        sweep.Result.get_fields_and_field_types())
