"""`touchroller contacts`: a recorded bag with known taps -> CSV rows with the right stamps and points."""
from __future__ import annotations

import csv
import os
import subprocess
import sys

import numpy as np
import pytest

from touchroller_bringup.cli import main
from touchroller_driver.sim.taps import TapRenderer
from touchroller_perception.geometry import CameraModel

CAMERA = CameraModel(fx=200.0, fy=200.0, cx=159.5, cy=119.5, width=320, height=240, theta=0.03, d=0.001)


@pytest.fixture(params=["sqlite3", "mcap"])
def tapped_bag(bag_factory, request):
    renderer = TapRenderer(CAMERA, seed=3)
    rng = np.random.default_rng(1)
    truth = CAMERA.surface_point(np.array([-0.01, 0.015]), np.array([0.1, -0.2]))
    uv, _ = CAMERA.project(truth)
    records = [(1_000_000 * i, renderer.render([], rng)) for i in range(5)]
    records += [(1_000_000 * 5, renderer.render([], rng)),            # no contact: no row
                (1_000_000 * 6, renderer.render([uv[0]], rng)),
                (1_000_000 * 7, renderer.render(uv, rng))]           # two contacts at once
    return bag_factory(records, storage=request.param), truth


def _read(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def test_contacts_csv_with_calibration(tapped_bag, tmp_path, capsys):
    bag, truth = tapped_bag
    params = tmp_path / "cal.yaml"
    CAMERA.to_yaml(params)
    out = tmp_path / "out" / "contacts.csv"
    assert main(["contacts", str(bag), "--params", str(params), "--out", str(out)]) == 0
    rows = _read(out)
    assert list(rows[0])[:6] == ["stamp_ns", "u", "v", "x", "y", "z"]
    assert [int(r["stamp_ns"]) for r in rows] == [6_000_000, 7_000_000, 7_000_000]
    for row in rows:
        point = np.array([float(row[k]) for k in "xyz"])
        assert min(np.linalg.norm(point - t) for t in truth) < 0.3e-3
        assert 0 < float(row["var_x"]) < 1e-6
    assert "3 contacts" in capsys.readouterr().out


def test_contacts_without_calibration_give_nan_points(tapped_bag, tmp_path):
    bag, _ = tapped_bag
    out = tmp_path / "contacts.csv"
    assert main(["contacts", str(bag), "--out", str(out), "--method", "paper"]) == 0
    rows = _read(out)
    assert rows and all(r["x"] == "nan" and r["z"] == "nan" for r in rows)
    assert all(float(r["u"]) > 0 for r in rows)


@pytest.mark.parametrize("extra, message", [
    (["--params", "/nonexistent.yaml"], "no such calibration file"),
    (["--reference-frames", "50"], "the reference needs 50"),
    (["--reference-frames", "0"], "--reference-frames must be in [1, 1000]"),
    (["--topic", "/other"], "no topic /other"),
    (["--threshold-sigma", "-1"], "threshold_sigma must be positive"),
    (["--pixel-sigma", "nan"], "--pixel-sigma"),
])
def test_bad_input_is_one_line(tapped_bag, tmp_path, capsys, extra, message):
    bag, _ = tapped_bag
    code = main(["contacts", str(bag), "--out", str(tmp_path / "c.csv"), *extra])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_missing_bag_is_one_line(tmp_path, capsys):
    assert main(["contacts", str(tmp_path / "nope"), "--out", str(tmp_path / "c.csv")]) == 2
    assert "no such bag" in capsys.readouterr().err


def test_simulated_taps_end_to_end(bag_factory, tmp_path):
    sim = pytest.importorskip("touchroller_driver.sim")
    sensor = sim.SimulatedSensor(sim.load_scene("contact_localisation", **{"motion.repeats": 1}), seed=1)
    frames = list(sensor.frames())
    bag = bag_factory([(f.stamp_ns, f.image) for f in frames])
    truth = {f.stamp_ns: [np.asarray(c["point"]) for c in f.truth["contacts"]] for f in frames}
    params = tmp_path / "truth.yaml"
    sensor.camera.to_yaml(params)
    out = tmp_path / "contacts.csv"
    assert main(["contacts", str(bag), "--params", str(params), "--out", str(out)]) == 0
    rows = _read(out)
    assert len(rows) == sum(len(points) for points in truth.values()) > 0
    errors = [min(np.linalg.norm(np.array([float(r[k]) for k in "xyz"]) - p) for p in truth[int(r["stamp_ns"])])
              for r in rows]
    assert np.mean(errors) < 0.25e-3      # the goal with exact calibration


def test_contact_columns_follow_the_point_columns(tapped_bag, tmp_path):
    from touchroller_bringup.commands.contacts import COLUMNS

    bag, _ = tapped_bag
    out = tmp_path / "contacts.csv"
    assert main(["contacts", str(bag), "--out", str(out)]) == 0
    rows = _read(out)
    assert tuple(rows[0]) == COLUMNS
    assert list(COLUMNS[:11]) == ["stamp_ns", "u", "v", "x", "y", "z", "score", "area", "major_axis",
                                  "minor_axis", "angle"]
    for row in rows:
        assert float(row["score"]) >= 12.0 and float(row["area"]) >= 100.0
        assert 0 < float(row["minor_axis"]) <= float(row["major_axis"])
        assert -np.pi / 2 < float(row["angle"]) <= np.pi / 2


def test_reference_from_another_recording(bag_factory, tmp_path, capsys):
    renderer = TapRenderer(CAMERA, seed=3)
    rng = np.random.default_rng(2)
    uv, _ = CAMERA.project(CAMERA.surface_point(np.array([0.0]), np.array([0.1])))
    reference = bag_factory([(1_000 * i, renderer.render([], rng)) for i in range(3)])
    # every frame of the run is a contact frame: none is spent on the reference
    run = bag_factory([(1_000_000 * i, renderer.render(uv, rng)) for i in range(4)])
    out = tmp_path / "contacts.csv"
    assert main(["contacts", str(run), "--reference-bag", str(reference), "--reference-frames", "3",
                 "--out", str(out)]) == 0
    rows = _read(out)
    assert [int(r["stamp_ns"]) for r in rows] == [0, 1_000_000, 2_000_000, 3_000_000]
    assert "4 frames" in capsys.readouterr().out
    small = bag_factory([(0, renderer.render([], rng)[:120, :160])])
    code = main(["contacts", str(small), "--reference-bag", str(reference), "--reference-frames", "3",
                 "--out", str(tmp_path / "c.csv")])
    err = capsys.readouterr().err
    assert code == 2 and "does not match the reference" in err and len(err.strip().splitlines()) == 1


def touchroller(*argv, cwd):
    """The `touchroller` console script, run as a user runs it."""
    executable = os.path.join(os.path.dirname(sys.executable), "touchroller")
    return subprocess.run([executable, *map(str, argv)], cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("content, message", [
    ("/**:\n  ros__parameters:\n    extrinsics.theta: 10\n", "extrinsics.theta = 10 rad is outside its range"),
    ("camera.fx: [\n", "not a YAML parameters file"),
    ("\tcamera.fx: 500\n", "not a YAML parameters file"),
])
def test_a_params_file_out_of_range_or_not_yaml_is_one_line_and_no_csv(tapped_bag, tmp_path, content, message):
    """theta 10 (degrees meant) gave rc 0 and points on the far side of the cylinder; a file that is not
    YAML gave PyYAML's multi-line report."""
    bag, _ = tapped_bag
    params = tmp_path / "cal.yaml"
    params.write_text(content)
    done = touchroller("contacts", bag, "--params", params, "--out", "c.csv", cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr and len(done.stderr.splitlines()) == 1, done.stderr
    assert not (tmp_path / "c.csv").exists()


def test_reference_frames_are_bounded(tapped_bag, tmp_path, capsys):
    bag, _ = tapped_bag
    assert main(["contacts", str(bag), "--out", str(tmp_path / "c.csv"), "--reference-frames", "100000000"]) == 2
    assert "--reference-frames must be in [1, 1000]" in capsys.readouterr().err


@pytest.mark.parametrize("failure, message", [
    ("missing_bag", "no such bag"),
    ("reference", "the reference needs 50"),
])
def test_a_failing_run_leaves_an_existing_csv_untouched(tapped_bag, tmp_path, failure, message):
    """`contacts` opened (truncated) --out before it read the bag: a failing run destroyed the CSV."""
    bag, _ = tapped_bag
    out = tmp_path / "out" / "contacts.csv"
    out.parent.mkdir()
    out.write_text("stamp_ns,u,v,x,y,z\n1,2,3,4,5,6\n")
    argv = [tmp_path / "no_such_bag" if failure == "missing_bag" else bag, "--out", out]
    argv += ["--reference-frames", "50"] if failure == "reference" else []
    done = touchroller("contacts", *argv, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr, done.stderr
    assert out.read_text() == "stamp_ns,u,v,x,y,z\n1,2,3,4,5,6\n"
    assert [p.name for p in out.parent.iterdir()] == ["contacts.csv"]


def test_a_calibration_of_another_image_size_is_refused_like_map_does(tapped_bag, tmp_path, capsys):
    """#28: a 320x240 calibration was applied to 640x480 images without a word."""
    bag, _ = tapped_bag
    params = tmp_path / "cal.yaml"
    CAMERA.replace(width=640, height=480, cx=319.5, cy=239.5).to_yaml(params)
    out = tmp_path / "c.csv"
    assert main(["contacts", str(bag), "--out", str(out), "--params", str(params)]) == 2
    err = capsys.readouterr().err
    assert "is for 640x480 images but" in err and "320x240" in err
    assert not out.exists()


def test_a_boolean_focal_length_is_refused_not_taken_as_one(tapped_bag, tmp_path, capsys):
    """#28: `camera.fx: true` was read as 1.0: every point NaN while the summary said cylinder points."""
    bag, _ = tapped_bag
    params = tmp_path / "cal.yaml"
    CAMERA.to_yaml(params)
    params.write_text(params.read_text().replace(f"camera.fx: {CAMERA.fx}", "camera.fx: true"))
    assert "camera.fx: true" in params.read_text()
    assert main(["contacts", str(bag), "--out", str(tmp_path / "c.csv"), "--params", str(params)]) == 2
    assert "camera.fx must be a number, got bool" in capsys.readouterr().err


def test_a_huge_pixel_sigma_is_one_line(tapped_bag, tmp_path, capsys):
    bag, _ = tapped_bag
    assert main(["contacts", str(bag), "--out", str(tmp_path / "c.csv"), "--pixel-sigma", "1e300"]) == 2
    assert "--pixel-sigma must be" in capsys.readouterr().err


@pytest.mark.parametrize("disk", ["full", "read_only"])
def test_a_full_or_read_only_disk_is_one_line_naming_the_output(tapped_bag, mount_tmpfs, disk, capsys):
    bag, _ = tapped_bag
    folder = mount_tmpfs("16k", free_bytes=0) if disk == "full" else mount_tmpfs("16k", read_only=True)
    out = folder / "contacts.csv"
    assert main(["contacts", str(bag), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert str(out) in err and ("disk is full" in err if disk == "full" else "read-only" in err), err
    assert not [p for p in folder.iterdir() if p.name.startswith(".contacts")]


def test_sigterm_leaves_no_temporary_and_the_next_run_sweeps_a_killed_runs(bag_factory, tmp_path):
    """#28: SIGTERM to contacts left `.contacts.csv.xxxx.csv` behind; SIGKILL cannot be handled, so the
    next run removes the temporaries no live writer holds."""
    import signal
    import time

    rng = np.random.default_rng(0)
    bag = bag_factory([(k * 1_000_000, rng.integers(0, 255, (240, 320, 3), np.uint8)) for k in range(300)])
    out = tmp_path / "contacts.csv"
    for sig in (signal.SIGTERM, signal.SIGKILL):
        process = subprocess.Popen([sys.executable, "-m", "touchroller_bringup.cli", "contacts", str(bag),
                                    "--out", str(out)], stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(".contacts.csv.*")) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert list(tmp_path.glob(".contacts.csv.*")), "the run never started writing"
        process.send_signal(sig)
        _, err = process.communicate(timeout=30)
        assert process.returncode in (128 + sig, -sig), err
        if sig == signal.SIGTERM:
            assert "Traceback" not in err and "stopped by SIGTERM" in err, err
            assert not list(tmp_path.glob(".contacts.csv.*"))
    assert list(tmp_path.glob(".contacts.csv.*")), "SIGKILL leaves its temporary"
    bag_small = bag_factory([(k * 1_000_000, rng.integers(0, 255, (24, 32, 3), np.uint8)) for k in range(8)])
    assert main(["contacts", str(bag_small), "--out", str(out)]) == 0
    assert not list(tmp_path.glob(".contacts.csv.*")) and out.is_file()


def test_a_compressed_recording_gives_the_same_contacts(tapped_bag, tmp_path):
    """`touchroller record` stores images as PNG on image_raw/compressed: the same rows as from the raw bag."""
    from touchroller_bringup.bag_compression import compress_recording

    bag, _ = tapped_bag
    compressed = tmp_path / "compressed"
    compress_recording(bag, compressed, storage="sqlite3")
    params = tmp_path / "cal.yaml"
    CAMERA.to_yaml(params)
    for source, out in ((bag, tmp_path / "raw.csv"), (compressed, tmp_path / "png.csv")):
        assert main(["contacts", str(source), "--params", str(params), "--out", str(out)]) == 0
    assert _read(tmp_path / "png.csv") == _read(tmp_path / "raw.csv") and len(_read(tmp_path / "raw.csv")) == 3
