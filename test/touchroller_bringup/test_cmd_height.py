"""`touchroller calibrate photometric` and `touchroller height` on the simulator's ball presses (an image
folder, the roller's camera model through --params), and their one-line refusals."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from touchroller_bringup.cli import main

sim = pytest.importorskip("touchroller_driver.sim")


@pytest.fixture(scope="module")
def pressed(tmp_path_factory):
    root = tmp_path_factory.mktemp("presses")
    sensor = sim.SimulatedSensor(sim.load_scene("ball_presses", **{"motion.presses": 8}), seed=2)
    refs, lines = [], ["image,u,v,radius_px"]
    (root / "presses").mkdir()
    for k, frame in enumerate(sensor.frames()):
        if frame.truth["phase"] == "reference":
            refs.append(frame.image)
        elif frame.truth["phase"] == "press":
            contact = frame.truth["contacts"][0]
            name = f"press_{k:03d}.png"
            cv2.imwrite(str(root / "presses" / name), frame.image)
            lines.append(f"{name},{contact['pixel'][0] + 1.0},{contact['pixel'][1] - 1.0},{contact['radius_px'] * 1.1}")
    cv2.imwrite(str(root / "ref.png"), np.median(np.stack(refs), axis=0).astype(np.uint8))
    (root / "labels.csv").write_text("\n".join(lines) + "\n")
    sensor.camera.to_yaml(root / "cal.yaml")
    return root


def test_calibrate_then_height_on_the_roller(pressed, capsys):
    root = pressed
    out = root / "photometric.npz"
    assert main(["calibrate", "photometric", str(root / "presses"), "--labels", str(root / "labels.csv"),
                 "--reference", str(root / "ref.png"), "--ball-radius", "0.004", "--params", str(root / "cal.yaml"),
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "8 presses" in text and "normal-angle residual median" in text and out.is_file()
    heights = root / "heights"
    assert main(["height", str(root / "presses"), "--photometric", str(out), "--reference", str(root / "ref.png"),
                 "--params", str(root / "cal.yaml"), "--out", str(heights)]) == 0
    files = sorted(heights.glob("*.tiff"))
    assert len(files) == 8
    z = tifffile.imread(files[0])
    assert z.dtype == np.float32 and z.shape == (480, 640)
    rows = np.isfinite(z).any(axis=1)
    assert 0 < rows.sum() < 480 and np.isnan(z[~rows]).all()          # only the contact band
    assert 2e-4 < np.nanmax(z) < 1.2e-3                                 # a 0.6 mm press, in metres


def test_height_flat_pixel_size_whole_frame(pressed):
    root = pressed
    out = root / "photometric.npz"
    if not out.is_file():
        pytest.skip("needs the calibration of the test above")
    heights = root / "flat"
    image = sorted((root / "presses").glob("*.png"))[0]
    assert main(["height", str(image), "--photometric", str(out), "--reference", str(root / "ref.png"),
                 "--pixel-size", "1.3e-4", "--out", str(heights)]) == 0
    z = tifffile.imread(heights / f"{image.stem}.tiff")
    assert np.isfinite(z).all() and z.shape == (480, 640)


def test_height_reads_with_the_models_zero_slope_prior_unless_told(pressed, capsys, tmp_path):
    """The calibration stores the prior's threshold (none with --still-quantile 0); `touchroller height` reads
    with it by default and without it with --still-slope 0; a bad --still-slope is refused in one line."""
    from touchroller_perception.height import PhotometricModel

    root = pressed
    common = ["--labels", str(root / "labels.csv"), "--reference", str(root / "ref.png"), "--ball-radius", "0.004",
              "--params", str(root / "cal.yaml")]
    assert main(["calibrate", "photometric", str(root / "presses"), *common, "--out", str(tmp_path / "p.npz")]) == 0
    assert "zero-slope prior: slopes shorter than" in capsys.readouterr().out
    assert main(["calibrate", "photometric", str(root / "presses"), *common, "--still-quantile", "0", "--out",
                 str(tmp_path / "none.npz")]) == 0
    threshold = PhotometricModel.load(tmp_path / "p.npz").still_slope
    assert threshold > 0 and PhotometricModel.load(tmp_path / "none.npz").still_slope == 0.0
    image = sorted((root / "presses").glob("*.png"))[0]
    base = ["height", str(image), "--photometric", str(tmp_path / "p.npz"), "--reference", str(root / "ref.png"),
            "--pixel-size", "1.3e-4"]
    assert main([*base, "--out", str(tmp_path / "on")]) == 0
    assert main([*base, "--still-slope", "0", "--out", str(tmp_path / "off")]) == 0
    on, off = (tifffile.imread(tmp_path / d / f"{image.stem}.tiff") for d in ("on", "off"))
    assert not np.array_equal(on, off)
    capsys.readouterr()
    assert main([*base, "--still-slope", "-1", "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "--still-slope must be a slope in [0, 1]" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("change, message", [
    ({"--ball-radius": "-1"}, "--ball-radius must be a positive"),
    ({"--ball-radius": "0.0001"}, "not smaller than the ball"),
    ({"--labels": "missing.csv"}, "no such labels file"),
    ({"--reference": "missing.png"}, "no such reference image"),
    ({"--position-colour-degrees": "1,x"}, "comma-separated integers"),
    ({"--position-colour-degrees": "2,4"}, "each be 0..3"),
    ({"--still-quantile": "1.5"}, "--still-quantile must be in [0, 1)"),
])
def test_calibrate_refusals_are_one_line(pressed, capsys, change, message):
    root = pressed
    args = {"--labels": str(root / "labels.csv"), "--reference": str(root / "ref.png"), "--ball-radius": "0.004",
            "--params": str(root / "cal.yaml"), "--out": str(root / "x.npz")}
    for key, value in change.items():
        args[key] = value if not value.endswith((".csv", ".png")) else str(root / value)
    argv = ["calibrate", "photometric", str(root / "presses")] + [x for kv in args.items() for x in kv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (root / "x.npz").exists()


def test_bad_labels_and_model(pressed, capsys, tmp_path):
    root = pressed
    bad = tmp_path / "labels.csv"
    bad.write_text("name,x,y,r\na.png,1,2,3\n")
    assert main(["calibrate", "photometric", str(root / "presses"), "--labels", str(bad), "--reference",
                 str(root / "ref.png"), "--ball-radius", "0.004", "--pixel-size", "1e-4", "--out",
                 str(tmp_path / "p.npz")]) == 2
    assert "header must be image,u,v,radius_px" in capsys.readouterr().err
    bad.write_text("image,u,v,radius_px\nnot_there.png,1,2,3\n")
    assert main(["calibrate", "photometric", str(root / "presses"), "--labels", str(bad), "--reference",
                 str(root / "ref.png"), "--ball-radius", "0.004", "--pixel-size", "1e-4", "--out",
                 str(tmp_path / "p.npz")]) == 2
    assert "not_there.png" in capsys.readouterr().err
    fake = tmp_path / "fake.npz"
    fake.write_bytes(b"nope")
    assert main(["height", str(root / "presses"), "--photometric", str(fake), "--reference", str(root / "ref.png"),
                 "--pixel-size", "1e-4", "--out", str(tmp_path / "h")]) == 2
    assert "not a photometric model" in capsys.readouterr().err
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.zeros((480, 640), np.uint8))
    assert main(["calibrate", "photometric", str(root / "presses"), "--labels", str(root / "labels.csv"),
                 "--reference", str(grey), "--ball-radius", "0.004", "--pixel-size", "1e-4", "--out",
                 str(tmp_path / "p.npz")]) == 2
    assert "one channel cannot give slopes" in capsys.readouterr().err


def test_height_of_a_recording_names_files_by_stamp(pressed, bag_factory, tmp_path):
    root = pressed
    out = root / "photometric.npz"
    if not out.is_file():
        pytest.skip("needs the calibration of the first test")
    images = [cv2.imread(str(p)) for p in sorted((root / "presses").glob("*.png"))[:2]]
    bag = bag_factory([(1_000 + k, image) for k, image in enumerate(images)])
    assert main(["height", str(bag), "--photometric", str(out), "--reference", str(root / "ref.png"),
                 "--pixel-size", "1.3e-4", "--out", str(tmp_path / "h")]) == 0
    assert sorted(p.name for p in (tmp_path / "h").glob("*.tiff")) == ["1000.tiff", "1001.tiff"]


def test_calibrate_builds_the_reference_from_the_presses(pressed, capsys, tmp_path):
    """A no-contact image taken in another light (10 % darker) is refused by --reference-from auto for one
    built from the presses' far fields, which is written for `touchroller height`."""
    root = pressed
    ref = cv2.imread(str(root / "ref.png"))
    dark = tmp_path / "dark.png"
    cv2.imwrite(str(dark), np.rint(ref * 0.9).astype(np.uint8))
    base = ["calibrate", "photometric", str(root / "presses"), "--labels", str(root / "labels.csv"), "--reference",
            str(dark), "--ball-radius", "0.004", "--params", str(root / "cal.yaml"), "--out", str(tmp_path / "p.npz")]
    assert main(base + ["--reference-from", "auto"]) == 2
    err = capsys.readouterr().err
    assert "needs --reference-out" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p.npz").exists()
    built = tmp_path / "built.png"
    assert main(base + ["--reference-from", "auto", "--reference-out", str(built)]) == 0
    assert "built from the presses' far fields" in capsys.readouterr().out
    written = cv2.imread(str(built))
    assert written.shape == ref.shape
    away = np.median(np.abs(written.astype(float) - ref)), np.median(np.abs(ref * 0.9 - ref))
    assert away[0] < 0.3 * away[1]
    assert main(["height", str(root / "presses"), "--photometric", str(tmp_path / "p.npz"), "--reference", str(built),
                 "--params", str(root / "cal.yaml"), "--out", str(tmp_path / "h")]) == 0


def test_calibrate_chooses_the_position_colour_degree(pressed, capsys, tmp_path):
    root = pressed
    out = tmp_path / "p.npz"
    assert main(["calibrate", "photometric", str(root / "presses"), "--labels", str(root / "labels.csv"),
                 "--reference", str(root / "ref.png"), "--ball-radius", "0.004", "--params", str(root / "cal.yaml"),
                 "--position-colour-degrees", "0,1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "held-out normal-angle error by degree: 0: " in text and ", 1: " in text
    from touchroller_perception.height import PhotometricModel
    assert PhotometricModel.load(out).config.position_colour_degree in (0, 1)
