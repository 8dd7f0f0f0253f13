"""`touchroller simulate`: bag + ground truth, deterministic, one-line errors."""
import numpy as np
import pytest
import yaml

from touchroller_bringup.bags import read_images
from touchroller_bringup.cli import main
from touchroller_perception.geometry import CameraModel

QUICK = ["--set", "motion.duration=0.3", "--set", "motion.length=0.01", "--set", "motion.accel=1.0",
         "--set", "surface.length=0.02", "--set", "surface.resolution=1.0e-4"]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_simulate_writes_bag_and_truth(tmp_path, storage, capsys):
    out = tmp_path / "bag"
    assert main(["simulate", "surface_mapping", "--out", str(out), "--storage", storage, *QUICK]) == 0
    records = list(read_images(out))
    truth = yaml.safe_load((out / "ground_truth.yaml").read_text())
    assert len(records) == truth["frame_count"] == 10
    assert [r.stamp_ns for r in records] == [f["stamp_ns"] for f in truth["frames"]]
    assert records[0].image.shape == (480, 640, 3)
    assert CameraModel.from_yaml(out / "camera_truth.yaml") == CameraModel.from_params(truth["camera_truth"])
    assert (out / "ground_truth_surface.png").is_file()
    assert np.load(out / "ground_truth_surface.npy").max() == pytest.approx(truth["surface"]["max_height"])
    assert "10 frames" in capsys.readouterr().out


def test_simulate_is_deterministic_and_seeded(tmp_path):
    paths = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        out = tmp_path / name
        assert main(["simulate", "surface_mapping", "--out", str(out), "--seed", str(seed), *QUICK]) == 0
        paths.append(out)
    images = [[r.image for r in read_images(p)] for p in paths]
    assert all(np.array_equal(x, y) for x, y in zip(images[0], images[1], strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(images[0], images[2], strict=True))


def test_simulate_contact_scene_truth_has_contacts(tmp_path):
    out = tmp_path / "taps"
    assert main(["simulate", "contact_localisation", "--out", str(out), "--variant", "paper",
                 "--set", "motion.repeats=1"]) == 0
    truth = yaml.safe_load((out / "ground_truth.yaml").read_text())
    contacts = [c for f in truth["frames"] for c in f["contacts"]]
    assert len(contacts) == 2 * 3 * 3 * 3
    assert all(len(c["point"]) == 3 and len(c["pixel"]) == 2 for c in contacts)
    paper = CameraModel.from_yaml(out / "camera_paper.yaml")
    true = CameraModel.from_yaml(out / "camera_truth.yaml")
    assert paper.theta != true.theta and paper.d != true.d


@pytest.mark.parametrize("argv, message", [
    (["simulate", "nowhere_scene", "--out", "{tmp}/x"], "no scene"),
    (["simulate", "surface_mapping", "--out", "{tmp}/x", "--set", "motion.duration"], "KEY=VALUE"),
    (["simulate", "surface_mapping", "--out", "{tmp}/x", "--set", "effects=[sparkles]"], "unknown effects"),
    (["simulate", "surface_mapping", "--out", "{tmp}"], "already exists"),
])
def test_simulate_errors_are_one_line(tmp_path, capsys, argv, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_a_run_that_fails_part_way_leaves_no_partial_recording(tmp_path, capsys, monkeypatch):
    """A render interrupted after a few frames left a bag folder with part of the frames and no ground
    truth; now the folder appears whole or not at all."""
    from touchroller_driver.sim import SimulatedSensor

    frames = SimulatedSensor.frames

    def three_then_fail(self, *args, **kwargs):
        for index, frame in enumerate(frames(self, *args, **kwargs)):
            if index == 3:
                raise KeyboardInterrupt
            yield frame

    monkeypatch.setattr(SimulatedSensor, "frames", three_then_fail)
    assert main(["simulate", "surface_mapping", "--out", str(tmp_path / "bag"), *QUICK]) == 130
    assert not list(tmp_path.iterdir())
