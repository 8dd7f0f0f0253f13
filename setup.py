"""ament_python package touchroller_bringup: three import packages, launch and config data."""
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "touchroller_bringup"
HERE = Path(__file__).resolve().parent


def data_tree(folder: str) -> list[tuple[str, list[str]]]:
    """(install dir, files) pairs mirroring `folder` under share/<package>/."""
    entries: list[tuple[str, list[str]]] = []
    if not (HERE / folder).is_dir():
        return entries
    for directory in sorted(p for p in (HERE / folder).rglob("*") if p.is_dir()) + [HERE / folder]:
        files = sorted(str(f.relative_to(HERE)) for f in directory.iterdir() if f.is_file())
        if files:
            entries.append((f"share/{PACKAGE}/{directory.relative_to(HERE)}", files))
    return entries


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["touchroller_driver*", "touchroller_perception*", "touchroller_bringup*"]),
    package_data={"touchroller_driver": ["data/*", "data/**/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        *data_tree("launch"),
        *data_tree("config"),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="TouchRoller ROS 2 maintainers",
    maintainer_email="touchroller@example.org",
    description="ROS 2 software for the TouchRoller rolling optical tactile sensor",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "touchroller = touchroller_bringup.cli:main",
            "camera_node = touchroller_bringup.ros_main:camera_node",
            "sweep_node = touchroller_bringup.ros_main:sweep_node",
            "perception_node = touchroller_bringup.ros_main:perception_node",
            "calibration_node = touchroller_bringup.ros_main:calibration_node",
        ],
    },
)
