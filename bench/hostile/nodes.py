"""Hostile probes of the nodes' start-up parameters (#28 group 2: perception, camera, calibration; the sweep
node's are the arm's probes), and the round-1 set (truncated bags, bad values, a vanishing camera, malformed
images)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from bench._common import ROOT
from bench.hostile import _kit as kit
from bench.hostile.arm import _scan_refused
from bench.hostile.probe import Probe


def _start(script: str, *arguments: str, words: tuple[str, ...] = (), make=None):
    """The node's console script with these arguments stops at start-up: one line, exit 2."""
    def check(scratch: Path) -> str | None:
        extra = make(scratch) if make is not None else ()
        done = kit.node(script, *arguments, *extra, cwd=scratch, timeout=60)
        return kit.one_line(done, 2, f"{script}: error", *words)
    return check


def _tf_only_bag(scratch: Path) -> tuple[str, ...]:
    from touchroller_bringup.bags import TransformRecord, write_scan

    write_scan(scratch / "tf_only", [TransformRecord("base", "tool0", k, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), False)
                                     for k in range(3)])
    return ("-p", "source:=bag", "-p", f"bag_path:={scratch / 'tf_only'}")


def _params_file(content: str):
    def make(scratch: Path) -> tuple[str, ...]:
        (scratch / "p.yaml").write_text(content)
        return ("--params-file", str(scratch / "p.yaml"))
    return make


def _resolution_as_text(scratch: Path) -> str | None:
    """`touchroller scan map.resolution:=1e-6`: YAML 1.1 reads 1e-6 as a string; it is the number."""
    from touchroller_bringup.commands.scan import _parse_value

    value = _parse_value("map.resolution", "1e-6")
    return None if value == 1e-6 and isinstance(value, float) else f"read as {value!r}"


def _truncated(command: str, storage: str):
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch, frames=40, storage=storage)
        storage_file = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
        with open(storage_file, "r+b") as stream:
            stream.truncate(storage_file.stat().st_size // 2)
        argv = {"replay": ["replay", bag, "--rate", "100"], "contacts": ["contacts", bag, "--out", scratch / "c.csv"],
                "map": ["map", bag, "--strip", "--out", scratch / "m.png"]}[command]
        done = kit.touchroller(*argv, timeout=120)
        if done.returncode == 0:
            return None if storage == "sqlite3" and command != "replay" else f"exit 0: {done.stdout.strip()[-200:]}"
        return kit.one_line(done, (1, 2), str(bag))
    return check


def _round_one_test(name: str):
    """A round-1 scenario as its test replays it (a node in-process on a real rclpy graph)."""
    def check(scratch: Path) -> str | None:
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                               f"test/touchroller_bringup/test_reliability.py::{name}"], cwd=ROOT,
                              capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            return (done.stdout.strip().splitlines() or ["no output"])[-1]
        return None
    return check


def probes() -> list[Probe]:
    P = Probe
    stop = "stops at start-up: one line, exit 2"
    return [
        P("perception map.bounds inverted", "parameters", stop,
          _start("perception_node", "-p", "map.bounds:=[0.5, 0.0, 0.4, 0.1]", words=("map bounds",))),
        P("perception map.bounds NaN", "parameters", stop,
          _start("perception_node", "-p", "map.bounds:=[.nan, 0.0, 0.4, 0.1]", words=("finite",))),
        P("perception map.bounds huge", "parameters", stop,
          _start("perception_node", "-p", "map.bounds:=[-1000.0, -1000.0, 1000.0, 1000.0]", words=("pixels",))),
        P("perception map.bounds with 3 numbers", "parameters", stop,
          _start("perception_node", "-p", "map.bounds:=[0.0, 0.0, 0.4]", words=("needs 4 values",))),
        P("perception camera.fx: true", "parameters", stop,
          _start("perception_node", "-p", "camera.fx:=true", words=("camera.fx",))),
        P("perception contacts.frame_id ''", "parameters", stop,
          _start("perception_node", "-p", "contacts.frame_id:=''", words=("contacts.frame_id",))),
        P("map.resolution:=1e-6 on the scan's command line", "parameters", "taken as the number 1e-6",
          _resolution_as_text),
        P("touchroller scan map.resolution:=1e-6 (no band fits on the map)", "parameters",
          "exit 2, one line naming map.resolution and the finest that fits, no output folder left (it rolled the "
          "whole sweep, then a traceback and a hang)", _scan_refused("map.resolution:=1e-6", "map.resolution",
                                                                     "at least")),
        P("calibration target bogus", "parameters", stop,
          _start("calibration_node", "-p", "target:=bogus", words=("target must be one of",))),
        P("calibration board.square NaN", "parameters", stop,
          _start("calibration_node", "-p", "board.square:=.nan", words=("board.square",))),
        P("calibration image_topic not a ROS name", "parameters", stop,
          _start("calibration_node", "-p", "image_topic:='bad topic'", words=("image_topic",))),
        P("camera source V4L2 (a case typo)", "parameters", stop + "; never the simulator",
          _start("camera_node", "-p", "source:=V4L2", words=("source must be one of",))),
        P("camera source bogus", "parameters", stop,
          _start("camera_node", "-p", "source:=bogus", words=("source must be one of",))),
        P("camera a missing video", "parameters", stop,
          _start("camera_node", "-p", "source:=video", "-p", "video_path:=/nonexistent/clip.avi",
                 words=("does not exist",))),
        P("camera a missing bag", "parameters", stop,
          _start("camera_node", "-p", "source:=bag", "-p", "bag_path:=/nonexistent/bag", words=("does not exist",))),
        P("camera a bag without images", "parameters", stop,
          _start("camera_node", words=("no images on",), make=_tf_only_bag)),
        P("camera a missing scene", "parameters", stop,
          _start("camera_node", "-p", "source:=sim", "-p", "scene:=no_such_scene", words=("scene",))),
        P("camera sim.motion bogus", "parameters", stop,
          _start("camera_node", "-p", "source:=sim", "-p", "sim.motion:=bogus", words=("sim.motion",))),
        P("camera frame_id ''", "parameters", stop,
          _start("camera_node", "-p", "source:=sim", "-p", "frame_id:=''", words=("frame_id",))),
        P("camera frame_prefix without its slash", "parameters", stop,
          _start("camera_node", "-p", "source:=sim", "-p", "frame_prefix:=left", words=("frame_prefix",))),
        P("node --params-file that is a YAML list", "parameters", stop + " (was RCLInvalidROSArgsError)",
          _start("perception_node", words=("not a ROS 2 parameters file",), make=_params_file("- a\n- b\n"))),
        P("round 1: replay of a truncated sqlite3 bag", "round 1", "one line naming the bag, exit non-zero",
          _truncated("replay", "sqlite3")),
        P("round 1: replay of a truncated MCAP bag", "round 1", "one line naming the bag, exit non-zero",
          _truncated("replay", "mcap")),
        P("round 1: contacts on a truncated MCAP bag", "round 1", "one line naming the bag, exit non-zero",
          _truncated("contacts", "mcap")),
        P("round 1: map on a truncated MCAP bag", "round 1", "one line naming the bag, exit non-zero",
          _truncated("map", "mcap")),
        P("round 1: camera node on a truncated bag", "round 1", "reports the stopped source and keeps serving",
          _round_one_test("test_camera_node_on_a_truncated_bag_reports_and_keeps_serving")),
        P("round 1: bad parameter values at run time", "round 1", "rejected, the old values kept",
          _round_one_test("test_bad_parameter_values_are_rejected_and_keep_the_old_values")),
        P("round 1: a camera that vanishes", "round 1", "reconnected, publishing resumes",
          _round_one_test("test_camera_that_vanishes_is_reconnected_and_publishing_resumes")),
        P("round 1: malformed images to perception", "round 1", "dropped and counted, the node survives",
          _round_one_test("test_perception_node_survives_malformed_images")),
    ]
