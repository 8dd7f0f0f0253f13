"""`touchroller map`: a short simulated roll recorded to a bag -> a map of the right length."""
from __future__ import annotations

import csv
import os
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest

from touchroller_bringup.cli import main

TRAVEL = 0.02  # m rolled
MM_PER_PX = 0.1  # the default camera at the contact line


@pytest.fixture(scope="module")
def simulated_roll():
    from touchroller_driver.sim import SimulatedSensor, load_scene

    scene = load_scene("surface_mapping", variant="fast",
                       **{"motion.length": TRAVEL, "motion.duration": 1.5, "motion.accel": 0.1})
    sensor = SimulatedSensor(scene, seed=4)
    frames = list(sensor.frames())
    travel = np.array([f.truth["state"]["travel"] for f in frames])
    return [(f.stamp_ns, f.image) for f in frames], travel


@pytest.fixture
def roll_bag(simulated_roll, bag_factory):
    records, travel = simulated_roll
    return bag_factory(records), travel


def test_map_of_a_simulated_roll(roll_bag, tmp_path, capsys):
    bag, travel = roll_bag
    out, steps = tmp_path / "maps" / "map.png", tmp_path / "steps.csv"
    assert main(["map", str(bag), "--out", str(out), "--steps", str(steps)]) == 0
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.ndim == 2 and image.dtype == np.uint8
    true_px = (travel[-1] - travel[0]) * 1e3 / MM_PER_PX
    assert image.shape[0] == pytest.approx(true_px + 70, abs=3)
    with open(steps, newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == len(travel)
    position = np.array([float(r["position_px"]) for r in rows])
    # the surface moves up the image as the roller travels forward
    assert np.max(np.abs(-position - (travel - travel[0]) * 1e3 / MM_PER_PX)) < 1.0
    assert f"{len(travel)} frames" in capsys.readouterr().out


def test_paper_method_and_metric_scale(roll_bag, tmp_path):
    bag, travel = roll_bag
    native, metric = tmp_path / "paper.png", tmp_path / "metric.png"
    assert main(["map", str(bag), "--out", str(native), "--method", "paper"]) == 0
    assert main(["map", str(bag), "--out", str(metric), "--metric", "0.2"]) == 0
    a, b = cv2.imread(str(native), 0), cv2.imread(str(metric), 0)
    assert a is not None and b.shape[1] == pytest.approx(640 / 2, abs=2)
    assert b.shape[0] == pytest.approx(((travel[-1] - travel[0]) * 1e3 / MM_PER_PX + 70) / 2, abs=3)


def test_mcap_bag(simulated_roll, bag_factory, tmp_path):
    records, _ = simulated_roll
    bag = bag_factory(records[:12], storage="mcap")
    out = tmp_path / "m.png"
    assert main(["map", str(bag), "--out", str(out)]) == 0
    assert cv2.imread(str(out), 0).shape[1] >= 630  # columns every frame reached


@pytest.mark.parametrize("extra, message", [
    (["--out", "{tmp}/map.xyz"], "unknown image format"),
    (["--out", "{tmp}"], "is a directory"),
    (["--out", "{tmp}/m.png", "--metric", "-1"], "positive number"),
    (["--out", "{tmp}/m.png", "--params", "/nonexistent.yaml"], "no such calibration file"),
    (["--out", "{tmp}/m.png", "--topic", "/nope"], "no topic /nope"),
    (["--out", "{tmp}/m.png", "--band-rows", "2"], "--band-rows"),
])
def test_bad_input_is_one_line(roll_bag, tmp_path, capsys, extra, message):
    bag, _ = roll_bag
    argv = ["map", str(bag)] + [a.replace("{tmp}", str(tmp_path)) for a in extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_missing_bag(tmp_path, capsys):
    assert main(["map", str(tmp_path / "none"), "--out", str(tmp_path / "m.png")]) == 2
    assert "no such bag" in capsys.readouterr().err


def test_other_image_size_without_calibration(bag_factory, tmp_path):
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.normal(size=(400, 200)).astype(np.float32), (0, 0), 1.5)
    tex = np.clip(128 + 300 * tex, 0, 255).astype(np.uint8)
    records = [(i * 33_000_000, tex[200 - 3 * i:320 - 3 * i]) for i in range(30)]  # mono8, 120x200
    out = tmp_path / "small.png"
    assert main(["map", str(bag_factory(records)), "--out", str(out), "--steps", str(tmp_path / "s.csv")]) == 0
    with open(tmp_path / "s.csv", newline="") as stream:
        shifts = [float(r["shift_px"]) for r in csv.DictReader(stream)][1:]
    assert np.allclose(shifts, 3.0, atol=0.1)
    assert main(["map", str(bag_factory(records)), "--out", str(out), "--metric"]) == 2


def test_a_frame_of_another_size_is_one_line_naming_its_stamp(simulated_roll, bag_factory, tmp_path, capsys):
    """Bands are cut in the reader thread: its errors still reach the user as one line, nothing written."""
    records, _ = simulated_roll
    odd_stamp = records[5][0]
    broken = records[:5] + [(odd_stamp, records[5][1][:240])] + records[6:]
    out = tmp_path / "broken.png"
    assert main(["map", str(bag_factory(broken)), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"frame at stamp {odd_stamp}" in err and "frame size changed" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_a_recording_that_starts_lifted_off_gives_the_full_map(simulated_roll, bag_factory, tmp_path, capsys):
    """A real scan approaches from above: frames with no contact before the roll must not freeze the map."""
    from touchroller_driver.sim import SimulatedSensor, load_scene
    from touchroller_driver.sim.render import RollerState

    records, travel = simulated_roll
    scene = load_scene("surface_mapping", variant="fast",
                       **{"motion.length": TRAVEL, "motion.duration": 1.5, "motion.accel": 0.1})
    sensor = SimulatedSensor(scene, seed=4)
    lifted = sensor.render(RollerState(travel=float(travel[0]), depth=-0.002))
    first = records[0][0]
    lead_in = [(first - (12 - k) * 33_333_333, lifted) for k in range(12)]
    out = tmp_path / "led.png"
    assert main(["map", str(bag_factory(lead_in + records)), "--out", str(out)]) == 0
    true_px = (travel[-1] - travel[0]) * 1e3 / MM_PER_PX
    assert cv2.imread(str(out), 0).shape[0] == pytest.approx(true_px + 70, abs=3)
    assert f"{len(records) + 12} frames" in capsys.readouterr().out


def test_read_ahead_keeps_order_raises_in_place_and_stops_early():
    import threading
    import time

    from touchroller_bringup.commands.map import _read_ahead

    assert list(_read_ahead(iter(range(100)), depth=3)) == list(range(100))

    def failing():
        yield from range(5)
        raise ValueError("truncated")

    seen = []
    with pytest.raises(ValueError, match="truncated"):
        for item in _read_ahead(failing(), depth=2):
            seen.append(item)
    assert seen == [0, 1, 2, 3, 4]
    # in batches: the same items in the same order, the last short batch and the error in place
    assert list(_read_ahead(iter(range(100)), depth=3, batch=8)) == list(range(100))
    seen = []
    with pytest.raises(ValueError, match="truncated"):
        for item in _read_ahead(failing(), depth=2, batch=3):
            seen.append(item)
    assert seen == [0, 1, 2, 3, 4]

    produced = []

    def endless():
        k = 0
        while True:
            produced.append(k)
            yield k
            k += 1

    reader = _read_ahead(endless(), depth=2)
    assert next(reader) == 0
    deadline = time.monotonic() + 5.0   # the reader runs ahead of the consumer, up to the queue's depth
    while len(produced) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(produced) >= 3
    reader.close()   # the consumer stops early (an error while stitching): the reader thread ends too
    assert not any(t.name == "bag-reader" and t.is_alive() for t in threading.enumerate())
    assert len(produced) <= 5


def test_a_metric_scale_that_would_not_fit_in_memory_is_one_line_before_stitching(roll_bag, tmp_path):
    """`touchroller map --metric 1e-6` tried to allocate 1.7 PB after stitching the whole bag."""
    bag, _ = roll_bag
    executable = os.path.join(os.path.dirname(sys.executable), "touchroller")
    done = subprocess.run([executable, "map", str(bag), "--out", "m.png", "--metric", "1e-6"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "--metric must be" in done.stderr and "[0.001, 10]" in done.stderr and len(done.stderr.splitlines()) == 1
    assert not (tmp_path / "m.png").exists()


def test_a_metric_map_past_the_pixel_bound_is_refused_before_it_is_allocated(roll_bag, tmp_path, capsys, monkeypatch):
    from touchroller_perception import stitching

    bag, _ = roll_bag
    monkeypatch.setattr(stitching, "MAX_MAP_PIXELS", 100_000)   # the roll is 639x269 px at 0.1 mm/px
    assert main(["map", str(bag), "--out", str(tmp_path / "m.png"), "--metric", "0.05"]) == 2
    err = capsys.readouterr().err
    assert re.search(r"would be 12\d\dx5\d\d px, more than 100,000 pixels", err) and "coarser" in err, err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.png").exists()


@pytest.mark.parametrize("extra, message", [
    (["--band-rows", "100000000"], "--band-rows must be in [8, 4096]"),
    (["--search", "100000000"], "--search must be in [1, 4096]"),
    (["--params", "{tmp}/not_yaml.yaml"], "not a YAML parameters file"),
])
def test_sizes_and_params_are_checked_before_reading_the_bag(roll_bag, tmp_path, capsys, extra, message):
    bag, _ = roll_bag
    (tmp_path / "not_yaml.yaml").write_text("camera: {fx: 500\n")
    argv = ["map", str(bag), "--out", str(tmp_path / "m.png")] + [a.replace("{tmp}", str(tmp_path)) for a in extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_a_write_that_fails_part_way_leaves_the_old_map(roll_bag, mount_tmpfs, capfd):
    """On a full disk (a real tmpfs): the write fails part-way; the old map stays as it was, no libpng line."""
    bag, _ = roll_bag
    folder = mount_tmpfs("64k")
    out = folder / "map.png"
    cv2.imwrite(str(out), np.full((10, 20), 99, np.uint8))
    before = out.read_bytes()
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as stream:   # leave less than the new map needs
        try:
            stream.write(b"\0" * (64 * 1024))
        except OSError:
            pass
    assert main(["map", str(bag), "--out", str(out)]) == 2
    err = capfd.readouterr().err   # the process's stderr: libpng writes its own line there
    assert f"cannot write --out {out}" in err and "libpng" not in err, err
    assert out.read_bytes() == before and sorted(p.name for p in folder.iterdir()) == ["filler", "map.png"]
