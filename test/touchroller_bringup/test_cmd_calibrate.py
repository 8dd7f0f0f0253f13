"""`touchroller calibrate intrinsics|extrinsics` on simulated bags and image folders."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from touchroller_bringup.cli import main
from touchroller_perception.geometry import CameraModel

sim = pytest.importorskip("touchroller_driver.sim")


@pytest.fixture(scope="module")
def scenes():
    chess = sim.SimulatedSensor(sim.load_scene("calibration_chessboard", **{"motion.views": 12}), seed=3)
    hemi = sim.SimulatedSensor(sim.load_scene("calibration_hemispheres", **{"motion.presses": 6}), seed=3)
    return ([(f.stamp_ns, f.image) for f in chess.frames()], [(f.stamp_ns, f.image) for f in hemi.frames()],
            hemi.camera)


def test_intrinsics_corner_path_is_chosen_on_the_command_line(scenes, bag_factory, tmp_path, capsys):
    """--corners image keeps the corners found in the image (the previous path); the default refines
    them on the board's plane: both calibrate, from different corners."""
    chess, _, truth = scenes
    bag = bag_factory(chess)
    cameras = {}
    for corners in ("image", None):
        out = tmp_path / f"{corners}.yaml"
        extra = ["--corners", corners] if corners else []
        assert main(["calibrate", "intrinsics", str(bag), "--out", str(out), *extra]) == 0
        cameras[corners] = CameraModel.from_yaml(out)
        assert abs(cameras[corners].fx - truth.fx) < 1.5
    assert cameras["image"].fx != cameras[None].fx
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["calibrate", "intrinsics", str(bag), "--out", str(tmp_path / "x.yaml"), "--corners", "edges"])


def test_calibrate_bags_end_to_end(scenes, bag_factory, tmp_path, capsys):
    chess, hemi, truth = scenes
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", "intrinsics", str(bag_factory(chess)), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "intrinsics from 12/12 views" in printed
    # the simulated lens has no tangential terms: the fit shows none, so k1, k2 (+ k3 if held-out views want it)
    assert "tangential p1, p2: Wald statistic" in printed and "no evidence for them, left out" in printed
    assert "distortion model k1k2: held-out RMS" in printed and "<- chosen" in printed
    assert "   X [" in printed and "skew [" in printed and "corners TL TR BL BR:" in printed
    # while the views are read, each one's state and the coverage so far
    assert "view 1/12: board found; coverage: X " in printed and "view 12/12: board found" in printed
    intrinsics = CameraModel.from_yaml(out)
    assert abs(intrinsics.fx - truth.fx) < 1.5
    # the intrinsics also as camera_calibration_parsers' YAML beside it, for a camera driver's camera_info_url
    from touchroller_bringup.camera_info_files import read_camera_info

    camera_info = read_camera_info(tmp_path / "cal.camera_info.yaml")
    assert camera_info.matches(intrinsics) and camera_info.camera_name == "touchroller"
    assert f"wrote {out} and {tmp_path / 'cal.camera_info.yaml'}" in printed
    report = tmp_path / "report.yaml"
    assert main(["calibrate", "extrinsics", str(bag_factory(hemi, "mcap")), "--params", str(out),
                 "--out", str(out), "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "extrinsics from 6/6 images" in printed
    # the optional terms, each with its held-out margin, in the output, the YAML and the report
    assert "  method: terms chosen by held-out prediction" in printed
    assert "  term row balance: " in printed and "  term view rejection: " in printed
    result = CameraModel.from_yaml(out)
    assert result.fx == pytest.approx(intrinsics.fx)                 # intrinsics carried over
    assert abs(math.degrees(result.theta - truth.theta)) < 0.15
    assert abs(result.d - truth.d) < 0.1e-3
    params = yaml.safe_load(out.read_text())["/**"]["ros__parameters"]
    assert "calibration.sigma.fx" in params and "calibration.sigma.theta" in params
    assert any(line.startswith("row balance: ") for line in params["calibration.extrinsics_terms"])
    assert params["calibration.extrinsics_method"] == "terms chosen by held-out prediction"
    views = yaml.safe_load(report.read_text())["extrinsics"]["views"]
    assert len(views) == 6 and all(v["rms_px"] < 0.3 for v in views)
    choices = yaml.safe_load(report.read_text())["extrinsics"]["choices"]
    assert [c["term"] for c in choices] == ["row balance", "view rejection"]


def test_boards_in_the_middle_are_warned_about_while_reading_and_in_the_result(tmp_path, capsys):
    central = sim.SimulatedSensor(sim.load_scene("calibration_chessboard", "central", **{"motion.views": 8}), seed=2)
    folder = tmp_path / "boards"
    folder.mkdir()
    for k, frame in enumerate(central.frames()):
        cv2.imwrite(str(folder / f"{k:03d}.png"), frame.image)
    assert main(["calibrate", "intrinsics", str(folder), "--out", str(tmp_path / "cal.yaml")]) == 0
    printed = capsys.readouterr().out
    progress = [line for line in printed.splitlines() if line.startswith("  view ")]
    assert len(progress) == 8 and all("image corners 0/4" in line for line in progress)
    assert "corners TL TR BL BR: . . . ." in printed
    assert "warning: image corners not covered (top-left, top-right, bottom-left, bottom-right" in printed


def test_calibrate_image_folder_with_reference(scenes, tmp_path, capsys):
    _, hemi, truth = scenes
    folder = tmp_path / "presses"
    folder.mkdir()
    for k, (_, image) in enumerate(hemi[5:]):
        cv2.imwrite(str(folder / f"{k:03d}.png"), image)
    reference = tmp_path / "reference.png"
    cv2.imwrite(str(reference), np.median([img for _, img in hemi[:5]], axis=0).astype(np.uint8))
    params = tmp_path / "truth.yaml"
    truth.replace(theta=0.0, d=0.0).to_yaml(params)
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", "extrinsics", str(folder), "--params", str(params), "--reference", str(reference),
                 "--out", str(out)]) == 0
    assert abs(math.degrees(CameraModel.from_yaml(out).theta - truth.theta)) < 0.1
    # a lights-off frame: black here (no background of its own), so the same result as strengths relative to
    # the whole reference (without a lights-off frame the default measures the imprints' extent instead)
    dark = tmp_path / "dark.png"
    cv2.imwrite(str(dark), np.zeros_like(hemi[0][1]))
    with_dark = tmp_path / "cal_dark.yaml"
    assert main(["calibrate", "extrinsics", str(folder), "--params", str(params), "--reference", str(reference),
                 "--dark", str(dark), "--out", str(with_dark)]) == 0
    relative = tmp_path / "cal_relative.yaml"
    assert main(["calibrate", "extrinsics", str(folder), "--params", str(params), "--reference", str(reference),
                 "--imprint-strength", "relative", "--out", str(relative)]) == 0
    assert CameraModel.from_yaml(with_dark).theta == pytest.approx(CameraModel.from_yaml(relative).theta, abs=1e-9)
    assert abs(math.degrees(CameraModel.from_yaml(with_dark).theta - truth.theta)) < 0.1
    assert main(["calibrate", "extrinsics", str(folder), "--params", str(params), "--dark",
                 str(tmp_path / "missing.png"), "--out", str(with_dark)]) == 2
    assert "cannot read image" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["calibrate", "intrinsics", "/nonexistent", "--out", "x.yaml"], "no such input"),
    (["calibrate", "intrinsics", "{empty}", "--out", "x.yaml"], "no images"),
    (["calibrate", "intrinsics", "{blank}", "--out", "x.yaml"], "single chessboard image"),
    (["calibrate", "intrinsics", "{blank}", "--board", "7by7", "--out", "x.yaml"], "--board must look like"),
    (["calibrate", "intrinsics", "{blank}", "--camera-name", "left-cam", "--out", "x.yaml"],
     "--camera-name 'left-cam' must be letters, digits and _"),
    (["calibrate", "extrinsics", "{blank}", "--out", "x.yaml"], "required"),
])
def test_calibrate_errors_are_one_line(argv, message, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    argv = [a.format(empty=empty, blank=blank) for a in argv]
    with pytest.raises(SystemExit) if message == "required" else _nothing():
        code = main(argv)
        assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_calibrate_compare(tmp_path, capsys):
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    CameraModel().to_yaml(a)
    CameraModel(d=0.001).to_yaml(b)
    assert main(["calibrate", "compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "d +1.0000 mm" in out and "back-projections apart" in out
    CameraModel(width=320, height=240, cx=159.5, cy=119.5).to_yaml(b)
    assert main(["calibrate", "compare", str(a), str(b)]) == 2
    assert "different image sizes" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["calibrate", "intrinsics", "{blank}", "--params", "{not_yaml}", "--out", "x.yaml"], "not a YAML parameters file"),
    (["calibrate", "extrinsics", "{blank}", "--params", "{not_yaml}", "--out", "x.yaml"], "not a YAML parameters file"),
    (["calibrate", "extrinsics", "{blank}", "--params", "{theta10}", "--out", "x.yaml"], "extrinsics.theta = 10 rad"),
    (["calibrate", "extrinsics", "{blank}", "--params", "{good}", "--frame", "100000x100000", "--out", "x.yaml"],
     "at most 50 rows and columns"),
    (["calibrate", "intrinsics", "{blank}", "--board", "100000x100000", "--out", "x.yaml"], "at most 100x100"),
])
def test_bad_params_files_and_sizes_are_one_line_and_exit_2(argv, message, tmp_path, capsys):
    """A params file that is not YAML exited 1 with PyYAML's report; --frame 100000x100000 tried 74.5 GiB."""
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    files = {"not_yaml": "camera.fx: [\n", "theta10": "/**:\n  ros__parameters:\n    extrinsics.theta: 10\n",
             "good": "/**:\n  ros__parameters:\n    camera.fx: 500.0\n"}
    for name, text in files.items():
        (tmp_path / f"{name}.yaml").write_text(text)
    argv = [a.format(blank=blank, **{name: tmp_path / f"{name}.yaml" for name in files}) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err


@pytest.mark.parametrize("disk", ["full", "read_only"])
def test_calibrate_on_a_full_or_read_only_disk_names_the_file_and_exits_non_zero(scenes, bag_factory, mount_tmpfs,
                                                                                  disk, capsys):
    """#28: 'cannot write None' on a full disk, and once exit 0 having written nothing."""
    chess, _, _ = scenes
    bag = bag_factory(chess)
    folder = mount_tmpfs("16k", free_bytes=0) if disk == "full" else mount_tmpfs("16k", read_only=True)
    out = folder / "cal.yaml"
    assert main(["calibrate", "intrinsics", str(bag), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"cannot write --out {out}" in err and "None" not in err, err
    assert not out.exists() and not [p for p in folder.iterdir() if p.name.startswith(".cal")]


def test_a_missing_reference_is_our_line_alone(tmp_path):
    """#28: OpenCV printed its own WARN line before ours for a --reference that does not exist."""
    import subprocess
    import sys

    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((24, 32, 3), np.uint8))
    params = tmp_path / "p.yaml"
    CameraModel().to_yaml(params)
    done = subprocess.run([sys.executable, "-m", "touchroller_bringup.cli", "calibrate", "extrinsics", str(folder),
                           "--params", str(params), "--reference", str(tmp_path / "missing.png"), "--out",
                           str(tmp_path / "o.yaml")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"touchroller: error: cannot read image --reference "
                                                f"{tmp_path / 'missing.png'}: no such file"], done.stderr
