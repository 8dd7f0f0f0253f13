"""Hostile probes of the `touchroller` command line: outputs that would destroy inputs, raw exceptions,
full and read-only disks, silently wrong results, signals and what they leave behind (#28, groups 1 and
3-6)."""
from __future__ import annotations

import os
import signal
import stat
import subprocess
import time
from pathlib import Path

from bench.hostile import _kit as kit
from bench.hostile.probe import Probe

# -- outputs (group 1) --------------------------------------------------------------------------------

def _refused_bag_intact(out_of, argv_of, *words: str):
    """contacts/calibrate/map with --out somewhere in or at the input: refused in one line, bag unchanged."""
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch)
        before = kit.snapshot(bag)
        done = kit.touchroller(*argv_of(bag, out_of(bag)), cwd=scratch)
        verdict = kit.one_line(done, 2, *words)
        if kit.snapshot(bag) != before:
            return "the bag changed: " + (verdict or "and the command said nothing wrong")
        return verdict
    return check


def _storage(bag: Path) -> Path:
    return next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))


def _contacts(bag: Path, out: Path) -> list:
    return ["contacts", bag, "--out", out]


def _steps_same_as_out(scratch: Path) -> str | None:
    bag = kit.bag(scratch, frames=30, shape=(120, 160, 3))
    out = scratch / "x.png"
    verdict = kit.one_line(kit.touchroller("map", bag, "--strip", "--out", out, "--steps", out), 2, "same path")
    return verdict or (f"{out} was written" if out.exists() else None)


def _special_file(make, kind: str):
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch)
        target = make(scratch)
        if target is None:
            return f"not run: no {kind} here"
        test = {"a character device": stat.S_ISCHR, "a FIFO": stat.S_ISFIFO, "a directory": stat.S_ISDIR}[kind]
        verdict = kit.one_line(kit.touchroller("contacts", bag, "--out", target), 2, kind.split()[-1])
        if not test(os.stat(target).st_mode):
            return f"{target} is no longer {kind}"
        return verdict
    return check


def _device(scratch: Path) -> Path | None:
    """A private copy of /dev/full's device node (never the system's own: code from before the fix, run
    through HOSTILE_CODE, replaces the node it is given)."""
    try:
        os.mknod(scratch / "full", 0o666 | stat.S_IFCHR, os.makedev(1, 7))
    except OSError:
        return None
    return scratch / "full"


def _fifo(scratch: Path) -> Path:
    os.mkfifo(scratch / "pipe.csv")
    return scratch / "pipe.csv"


def _dir(scratch: Path) -> Path:
    (scratch / "folder.csv").mkdir()
    return scratch / "folder.csv"


def _symlink_to_storage(scratch: Path) -> str | None:
    bag = kit.bag(scratch)
    link = scratch / "innocent.csv"
    link.symlink_to(_storage(bag))
    before = kit.snapshot(bag)
    verdict = kit.one_line(kit.touchroller("contacts", bag, "--out", link), 2, "destroy the input")
    return ("the bag changed" if kit.snapshot(bag) != before else None) or verdict


def _simulate_over_a_file(scratch: Path) -> str | None:
    (scratch / "bag").write_text("keep me")
    verdict = kit.one_line(kit.touchroller("simulate", "surface_mapping", "--out", scratch / "bag", "--set",
                                           "motion.duration=3"), 2, "already exists")
    return verdict or (None if (scratch / "bag").read_text() == "keep me" else "the file was replaced")


def _scan_out_is_a_file(scratch: Path) -> str | None:
    (scratch / "out").write_text("keep me")
    verdict = kit.one_line(kit.touchroller("scan", "--out", scratch / "out", "--quiet", timeout=120), 2,
                           "not a folder")
    return verdict or (None if (scratch / "out").read_text() == "keep me" else "the file was replaced")


def _record_out_is_a_file(scratch: Path) -> str | None:
    (scratch / "out").write_text("keep me")
    verdict = kit.one_line(kit.touchroller("record", "--out", scratch / "out", "--duration", "1"), 2, "not a folder")
    return verdict or (None if (scratch / "out").read_text() == "keep me" else "the file was replaced")


# -- raw exceptions (group 3) -----------------------------------------------------------------------------

def _map_case(kind: str, *words: str):
    def check(scratch: Path) -> str | None:
        options = {"hour": {"tf_offset_ns": 3600 * 10**9}, "loop": {"loop": True}}.get(kind, {})
        bag, params = kit.tf_bag(scratch, **options)
        extra = {"resolution": ["--resolution", "1e-6"], "empty_frame": ["--world-frame", ""]}.get(kind, [])
        done = kit.touchroller("map", bag, "--params", params, "--out", scratch / "m.png", *extra)
        if kind == "loop":   # mapped, or refused in one line: never a raw exception
            if done.returncode == 0:
                return None
            return kit.one_line(done, 2)
        verdict = kit.one_line(done, 2, *words)
        if verdict is None and ("TypeError" in done.stderr or "ValueError" in done.stderr):
            return f"a raw exception: {done.stderr.strip()}"
        return verdict
    return check


def _pixel_sigma(scratch: Path) -> str | None:
    bag = kit.bag(scratch)
    return kit.one_line(kit.touchroller("contacts", bag, "--out", scratch / "c.csv", "--pixel-sigma", "1e300"), 2,
                        "--pixel-sigma")


def _params_is_a_directory(scratch: Path) -> str | None:
    bag = kit.bag(scratch)
    (scratch / "cal").mkdir()
    verdict = kit.one_line(kit.touchroller("contacts", bag, "--out", scratch / "c.csv", "--params", scratch / "cal"),
                           (1, 2), "cal")
    return verdict or ("IsADirectoryError" in kit.touchroller("contacts", bag, "--out", scratch / "c.csv",
                                                               "--params", scratch / "cal").stderr and "raw" or None)


def _missing_reference(scratch: Path) -> str | None:
    import cv2
    import numpy as np

    from touchroller_perception.geometry import CameraModel

    (scratch / "images").mkdir()
    cv2.imwrite(str(scratch / "images" / "a.png"), np.zeros((24, 32, 3), np.uint8))
    CameraModel().to_yaml(scratch / "p.yaml")
    done = kit.touchroller("calibrate", "extrinsics", scratch / "images", "--params", scratch / "p.yaml",
                           "--reference", scratch / "missing.png", "--out", scratch / "o.yaml")
    return kit.one_line(done, 2, "--reference", "no such file")


def _scan_params(content: str, *words: str):
    def check(scratch: Path) -> str | None:
        (scratch / "p.yaml").write_text(content)
        return kit.one_line(kit.touchroller("scan", scratch / "p.yaml", "--out", scratch / "o", "--quiet",
                                            timeout=120), 2, *words)
    return check


def _read_only(command: str):
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch)
        with kit.Mount(scratch, "64k", read_only=command != "reindex") as point:
            if point is None:
                return kit.NO_MOUNT
            if command == "contacts":
                return kit.one_line(kit.touchroller("contacts", bag, "--out", point / "c.csv"), (1, 2), "read-only")
            if command == "simulate":
                return kit.one_line(kit.touchroller("simulate", "surface_mapping", "--out", point / "b", "--set",
                                                    "motion.duration=3"), 2, "not writable")
            if command == "scan":
                return kit.one_line(kit.touchroller("scan", "--out", point / "o", "--quiet", timeout=180), (1, 2),
                                    "read-only")
            # reindex: a killed recording copied onto the tmpfs, then the tmpfs made read-only
            import shutil

            shutil.copytree(bag, point / "bag")
            (point / "bag" / "metadata.yaml").unlink()
            if subprocess.run(["mount", "-o", "remount,ro", str(point)], check=False).returncode != 0:
                return "not run: cannot remount the tmpfs read-only"
            return kit.one_line(kit.touchroller("reindex", point / "bag"), 2, "copy the bag")
    return check


# -- full disk (group 4) --------------------------------------------------------------------------------

def _full(command: str, *words: str, storage: str = "sqlite3"):
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch, frames=40, shape=(120, 160, 3))
        with kit.Mount(scratch, "64k", free_bytes=2048) as point:
            if point is None:
                return kit.NO_MOUNT
            argv = {"contacts": ["contacts", bag, "--out", point / "c.csv"],
                    "map": ["map", bag, "--strip", "--out", point / "m.png"],
                    "simulate": ["simulate", "surface_mapping", "--out", point / "b", "--set", "motion.duration=3",
                                 "--storage", storage],
                    "calibrate": ["calibrate", "intrinsics", _chessboard(scratch), "--out", point / "cal.yaml"]}
            done = kit.touchroller(*argv[command])
            verdict = kit.one_line(done, (1, 2), *words)
            if "libpng" in done.stderr:
                verdict = f"libpng's own line: {done.stderr.strip()}"
            left = [p.name for p in point.iterdir() if p.name != ".filler"]
            return verdict or (f"left behind: {left}" if left else None)
    return check


def _chessboard(scratch: Path) -> Path:
    from touchroller_bringup.bags import write_images
    from touchroller_driver.sim import SimulatedSensor, load_scene

    sensor = SimulatedSensor(load_scene("calibration_chessboard", **{"motion.views": 6}), seed=3)
    path = scratch / "chess"
    write_images(path, [(f.stamp_ns, f.image) for f in sensor.frames()])
    return path


def _scan_nearly_full(scratch: Path) -> str | None:
    """The scan's outputs on a disk with room for contacts.csv and report.md but not the map."""
    from types import SimpleNamespace

    import numpy as np

    from touchroller_bringup.graph import build_graph
    from touchroller_bringup.image_conversion import array_to_image
    from touchroller_bringup.scan import _Collected, _write_outputs

    with kit.Mount(scratch, "64k", free_bytes=24 * 1024) as point:
        if point is None:
            return kit.NO_MOUNT
        collected = _Collected()
        collected.contacts = [(k, 0.001 * k, 0.01, 0.02) for k in range(100)]
        collected.map_msg = array_to_image(np.random.default_rng(0).integers(0, 255, (400, 400), np.uint8), 0)
        perception = SimpleNamespace(world=None, camera=None, received=5, dropped=0, malformed=0,
                                     has_parameter=lambda name: False)
        result = _write_outputs(point, build_graph("scan", {}, []), perception, collected, "done", "ok", 1.0, "")
        written = sorted(p.name for p in point.iterdir() if not p.name.startswith("."))
        # the map and its preview in the report (a picture of it) are what does not fit
        if written != ["contacts.csv", "report.md"] or not {"map.png"} <= set(result.failed) <= {"map.png",
                                                                                                 "map_preview.png"}:
            return f"written {written}, failures named {result.failed}"
        return None


# -- silently wrong (group 5) -----------------------------------------------------------------------------

def _other_size_calibration(scratch: Path) -> str | None:
    from touchroller_perception.geometry import CameraModel

    bag = kit.bag(scratch, shape=(240, 320, 3))
    CameraModel().to_yaml(scratch / "cal.yaml")   # 640x480
    return kit.one_line(kit.touchroller("contacts", bag, "--out", scratch / "c.csv", "--params", scratch / "cal.yaml"),
                        2, "640x480", "320x240")


def _boolean_fx(scratch: Path) -> str | None:
    from touchroller_perception.geometry import CameraModel

    bag = kit.bag(scratch, shape=(480, 640, 3))
    camera = CameraModel()
    camera.to_yaml(scratch / "cal.yaml")
    text = (scratch / "cal.yaml").read_text().replace(f"camera.fx: {camera.fx}", "camera.fx: true")
    (scratch / "cal.yaml").write_text(text)
    return kit.one_line(kit.touchroller("contacts", bag, "--out", scratch / "c.csv", "--params", scratch / "cal.yaml"),
                        2, "camera.fx must be a number")


def _tf_without_static(scratch: Path) -> str | None:
    bag, params = kit.tf_bag(scratch, static=False)
    done = kit.touchroller("map", bag, "--params", params, "--out", scratch / "m.png")
    if done.returncode != 0:
        return f"exit {done.returncode}: {done.stderr.strip()}"
    for word in ("no /tf_static", "world map was skipped"):
        if word not in done.stderr:
            return f"said nothing of {word!r}: {done.stderr.strip() or 'silent'}"
    return None


# -- signals and leftovers (group 6) ----------------------------------------------------------------------

def _signal_contacts(sig: int):
    def check(scratch: Path) -> str | None:
        bag = kit.bag(scratch, frames=300, shape=(240, 320, 3))
        out = scratch / "c.csv"
        process = kit.popen(["contacts", str(bag), "--out", str(out)], stderr=subprocess.PIPE, text=True)
        if not kit.wait_for(lambda: bool(kit.hidden(scratch)), 60):
            process.kill()
            return "never started writing"
        process.send_signal(sig)
        _, err = process.communicate(timeout=60)
        if sig == signal.SIGKILL:   # cannot be handled: the next run sweeps the temporary
            small = kit.bag(scratch, name="small")
            done = kit.touchroller("contacts", small, "--out", out)
            return kit.hidden(scratch) and f"the next run left {kit.hidden(scratch)}" or \
                (None if done.returncode == 0 else done.stderr.strip())
        if "Traceback" in err:
            return "a traceback"
        if process.returncode != 128 + sig:
            return f"exit {process.returncode}: {err.strip()}"
        return f"left {kit.hidden(scratch)}" if kit.hidden(scratch) else None
    return check


def _map_reader_orphan(sig: int):
    def check(scratch: Path) -> str | None:
        bag, params = kit.tf_bag(scratch, frames=150)
        process = kit.popen(["map", str(bag), "--params", str(params), "--out", str(scratch / "m.png")],
                            stderr=subprocess.PIPE, text=True)
        found: list[int] = []
        if not kit.wait_for(lambda: bool(found.extend(kit.children(process.pid)) or found), 60):
            process.kill()
            process.communicate()
            return "not run: the map ended before its reader was seen" if process.returncode == 0 else \
                f"no reader seen (exit {process.returncode})"
        process.send_signal(sig)
        process.communicate(timeout=60)
        if not kit.wait_for(lambda: not any(kit.alive(pid) for pid in found), 10):
            for pid in found:
                if kit.alive(pid):
                    os.kill(pid, signal.SIGKILL)
            return f"the reader {found} outlived its parent"
        return f"left {kit.hidden(scratch)}" if kit.hidden(scratch) else None
    return check


def _early_sigint(scratch: Path) -> str | None:
    failures = []
    for delay in (0.1, 0.2, 0.3):
        process = kit.popen(["contacts", "x", "--out", "y"], stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=60)
        if "Traceback" in err:
            failures.append(f"a traceback after {delay} s")
    return "; ".join(failures) or None


def probes() -> list[Probe]:
    P = Probe
    refused = "refused in one line, exit 2, before any work; the bag unchanged"
    return [
        P("contacts --out the bag's storage file", "outputs", refused,
          _refused_bag_intact(_storage, _contacts, "destroy the input")),
        P("contacts --out BAG/metadata.yaml", "outputs", refused,
          _refused_bag_intact(lambda b: b / "metadata.yaml", _contacts, "inside the input")),
        P("calibrate intrinsics --out BAG/metadata.yaml", "outputs", refused,
          _refused_bag_intact(lambda b: b / "metadata.yaml",
                              lambda b, o: ["calibrate", "intrinsics", b, "--out", o], "INPUT")),
        P("map --steps X --out X", "outputs", "refused in one line (same path), nothing written", _steps_same_as_out),
        P("contacts --out a character device (as /dev/full)", "outputs", "refused in one line; the device stays a "
          "character device", _special_file(_device, "a character device")),
        P("contacts --out a FIFO", "outputs", "refused in one line; the FIFO stays a FIFO",
          _special_file(_fifo, "a FIFO")),
        P("contacts --out a directory", "outputs", "refused in one line; the directory stays",
          _special_file(_dir, "a directory")),
        P("contacts --out a symlink to the bag's storage", "outputs", refused, _symlink_to_storage),
        P("simulate --out an existing file", "outputs", "refused in one line; the file kept", _simulate_over_a_file),
        P("scan --out an existing file", "outputs", "refused in one line; the file kept", _scan_out_is_a_file),
        P("record --out an existing file", "outputs", "refused in one line; the file kept", _record_out_is_a_file),
        P("map with TF an hour after the images", "errors", "one line naming the TF and its times",
          _map_case("hour", "base -> tool0")),
        P("map --resolution 1e-6", "errors", "one line naming --resolution", _map_case("resolution", "--resolution")),
        P("map with a TF loop in /tf_static", "errors", "a map or one line, never a raw exception", _map_case("loop")),
        P("map --world-frame ''", "errors", "one line naming --world-frame",
          _map_case("empty_frame", "--world-frame must not be empty")),
        P("contacts --pixel-sigma 1e300", "errors", "one line naming --pixel-sigma (was OverflowError)", _pixel_sigma),
        P("contacts --params a directory", "errors", "one line naming the path (was IsADirectoryError)",
          _params_is_a_directory),
        P("calibrate extrinsics --reference missing.png", "errors", "our one line alone (no OpenCV WARN)",
          _missing_reference),
        P("scan params file that is a YAML list", "errors", "one line: not a ROS 2 parameters file (was "
          "RCLInvalidROSArgsError)", _scan_params("- a\n- b\n", "not a ROS 2 parameters file")),
        P("scan params file that is plain text", "errors", "one line: not a ROS 2 parameters file (was a scan "
          "run on defaults)", _scan_params("just text\n", "not a ROS 2 parameters file")),
        P("contacts into a read-only folder", "errors", "one line naming the file and read-only",
          _read_only("contacts")),
        P("simulate into a read-only folder", "errors", "one line before the render", _read_only("simulate")),
        P("scan into a read-only folder", "errors", "one line naming read-only", _read_only("scan")),
        P("reindex a bag on a read-only disk", "errors", "one line saying to copy the bag", _read_only("reindex")),
        P("contacts onto a full disk", "disk", "one line naming the file and the full disk; nothing left",
          _full("contacts", "c.csv", "disk is full")),
        P("map onto a full disk", "disk", "one line, no libpng line, nothing left", _full("map", "cannot write --out")),
        P("simulate (sqlite3) onto a full disk", "disk", "one line naming --out, nothing left (was OperationalError)",
          _full("simulate", "--out")),
        P("simulate (MCAP) onto a full disk", "disk", "one line naming --out, nothing left (was OSError)",
          _full("simulate", "--out", storage="mcap")),
        P("calibrate intrinsics onto a full disk", "disk", "one line naming --out, non-zero exit (was 'cannot write "
          "None', once exit 0)", _full("calibrate", "cannot write --out")),
        P("scan outputs on a nearly full disk", "disk", "contacts.csv and report.md written, the map (and its preview) "
          "named as failed",
          _scan_nearly_full),
        P("contacts with a calibration of another image size", "results", "refused in one line, as map does",
          _other_size_calibration),
        P("contacts with camera.fx: true", "results", "refused: a boolean is not a number", _boolean_fx),
        P("map of a recording with /tf but no /tf_static", "results", "says /tf_static is missing and the world map "
          "was skipped", _tf_without_static),
        P("SIGTERM to contacts while it writes", "signals", "exit 143, no traceback, no hidden temporary left",
          _signal_contacts(signal.SIGTERM)),
        P("SIGKILL to contacts, then a run of the same output", "signals", "the next run removes the killed run's "
          "temporary", _signal_contacts(signal.SIGKILL)),
        P("SIGTERM to map while its reader runs", "signals", "the forked reader dies with it; no temporary left",
          _map_reader_orphan(signal.SIGTERM)),
        P("SIGKILL to map while its reader runs", "signals", "the forked reader dies with it",
          _map_reader_orphan(signal.SIGKILL)),
        P("SIGINT 0.1-0.3 s after start", "signals", "no KeyboardInterrupt traceback", _early_sigint),
    ]
