"""The ament_python package itself: package.xml, colcon build, installed layout, ament index."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "touchroller_bringup"
NODE_EXECUTABLES = ("camera_node", "perception_node", "sweep_node", "calibration_node", "touchroller")


def test_package_xml_is_valid_format_3():
    from catkin_pkg.package import parse_package

    package = parse_package(ROOT / "package.xml")
    package.validate()                       # raises on an invalid manifest (colcon would fall back silently)
    assert package.package_format == 3
    assert package.name == PACKAGE
    assert package.get_build_type() == "ament_python"
    assert {d.name for d in package.exec_depends} >= {"rclpy", "sensor_msgs", "geometry_msgs", "diagnostic_msgs"}


def test_setup_cfg_installs_scripts_under_lib_package():
    import configparser

    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    assert config["develop"]["script_dir"] == f"$base/lib/{PACKAGE}"
    assert config["install"]["install_scripts"] == f"$base/lib/{PACKAGE}"
    assert (ROOT / "resource" / PACKAGE).is_file()


def _source_files() -> list[str]:
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout.split()
    return [f for f in listed if (ROOT / f).is_file()]


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        pytest.skip("colcon is not installed in this environment")
    workspace = tmp_path_factory.mktemp("ws")
    for name in _source_files():
        target = workspace / "src" / PACKAGE / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    result = subprocess.run([str(colcon), "build", "--base-paths", "src", "--event-handlers", "console_direct-"],
                            cwd=workspace, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return workspace / "install" / PACKAGE


def test_colcon_build_installs_index_marker_launch_and_executables(colcon_install):
    assert (colcon_install / "share/ament_index/resource_index/packages" / PACKAGE).is_file()
    assert (colcon_install / "share" / PACKAGE / "package.xml").is_file()
    assert (colcon_install / "share" / PACKAGE / "launch/scan.launch.py").is_file()
    assert (colcon_install / "share" / PACKAGE / "config/touchroller.yaml").is_file()
    for name in NODE_EXECUTABLES:
        script = colcon_install / "lib" / PACKAGE / name
        assert script.is_file() and os.access(script, os.X_OK), name


def test_ament_index_resolves_the_built_package(colcon_install):
    site = next((colcon_install / "lib").glob("python3*/site-packages"))
    env = dict(os.environ, AMENT_PREFIX_PATH=str(colcon_install), PYTHONPATH=str(site))
    code = ("from ament_index_python.packages import get_package_share_directory as g;"
            "from touchroller_driver.paths import share_dir;"
            f"print(g('{PACKAGE}')); print(share_dir())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    expected = str(colcon_install / "share" / PACKAGE)
    assert out.stdout.split() == [expected, expected]


def test_config_is_found_in_the_checkout_without_an_index(monkeypatch):
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    from touchroller_driver import paths

    assert paths.config_path("touchroller.yaml").is_file()


# Where each third-party module a runtime package imports comes from on a ROS 2 machine: the rosdep key
# package.xml must name (`rosdep install` installs it), or None for what package.xml documents as pip-only.
ROSDEP_KEYS = {
    "numpy": "python3-numpy", "cv2": "python3-opencv", "yaml": "python3-yaml", "scipy": "python3-scipy",
    "skimage": "python3-skimage", "PIL": "python3-pil",
    "rosbags": "python3-rosbags-pip",
    # rosbags' own dependencies, installed with it
    "ruamel": "python3-rosbags-pip", "lz4": "python3-rosbags-pip", "compression": "python3-rosbags-pip",
    "backports": "python3-rosbags-pip",
    # ur_rtde has no rosdep key: named in a package.xml comment and docs/ur5.md (pip install ur_rtde)
    "rtde_control": None, "rtde_receive": None, "dashboard_client": None,
    # tifffile (height and GeoTIFF maps) has no rosdep key either: pip install tifffile
    "tifffile": None,
    # isal (a faster inflate for compressed recordings) is optional, without a rosdep key: pip install isal
    "isal": None,
}
OWN = {"touchroller_bringup", "touchroller_perception", "touchroller_driver"}


def _runtime_imports() -> set[str]:
    import ast

    found: set[str] = set()
    for package in OWN:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    found |= {alias.name.split(".")[0] for alias in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    found.add(node.module.split(".")[0])
    return found - set(sys.stdlib_module_names) - OWN - {"__future__"}


def test_package_xml_names_what_rosdep_must_install_for_every_runtime_import():
    from catkin_pkg.package import parse_package

    declared = {d.name for d in parse_package(ROOT / "package.xml").exec_depends}
    missing = []
    for module in sorted(_runtime_imports()):
        if module in ROSDEP_KEYS:
            key = ROSDEP_KEYS[module]
            if key is not None and key not in declared:
                missing.append(f"{module} ({key})")
        elif module not in declared:   # ROS packages: rclpy, launch, *_msgs ... are their own keys
            missing.append(module)
    assert missing == []
    assert "pip install ur_rtde" in (ROOT / "package.xml").read_text()
    assert "pip install tifffile" in (ROOT / "package.xml").read_text()
    assert "pip install isal" in (ROOT / "package.xml").read_text()
    assert "pip install ur_rtde" in (ROOT / "docs" / "ur5.md").read_text()
