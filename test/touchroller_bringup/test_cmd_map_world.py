"""`touchroller map` on recordings with TF: the world map (map.png + map.yaml), offline, as the scan maps it."""
from __future__ import annotations

import gc
import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from touchroller_bringup.bags import ImageRecord, TransformRecord, write_scan
from touchroller_bringup.cli import main
from touchroller_bringup.map_files import read_world_map, write_world_map
from touchroller_perception.world_map import WorldMapImage

pytest.importorskip("touchroller_driver.sim")

_spec = importlib.util.spec_from_file_location(
    "sim_scans", Path(__file__).parents[1] / "touchroller_driver" / "sim" / "sim_scans.py")
assert _spec is not None and _spec.loader is not None
sim_scans = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sim_scans)
MOUNT = sim_scans.MOUNT
LATENCY = 0.03


@pytest.fixture(scope="module")
def scan_bag(tmp_path_factory):
    """A one-pass scan (3 cm at 20 mm/s) filmed 30 ms late, recorded with /tf and /tf_static."""
    sensor = sim_scans.large_surface(seed=1)
    plan = sim_scans.raster([0.45, -0.02, 0.03, 0.04])
    path = tmp_path_factory.mktemp("scan") / "bag"
    assert write_scan(path, sim_scans.bag_records(sim_scans.sweep(sensor, plan, LATENCY))) > 100
    return path


@pytest.mark.slow
def test_a_recording_with_tf_maps_into_the_world_frame(scan_bag, tmp_path, capsys):
    out = tmp_path / "map.png"
    assert main(["map", str(scan_bag), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "map.yaml" in printed and "map.tif" in printed and "1 pass(es)" in printed, printed
    assert "camera latency estimated " in printed, printed
    assert {p.name for p in tmp_path.iterdir()} == {"map.png", "map.yaml", "map.tif"}   # no tiles left behind
    estimated = float(printed.split("camera latency estimated ")[1].split(" ms")[0])
    assert estimated == pytest.approx(LATENCY * 1e3, abs=3.0)
    grey, alpha, meta = read_world_map(tmp_path / "map.yaml")
    assert set(meta) >= {"image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh", "frame_id"}
    assert meta["frame_id"] == "base" and meta["resolution"] == 1e-4 and meta["origin"][2] == 0.0
    assert grey.shape == alpha.shape and set(np.unique(alpha)) == {0, 255}
    mapped = alpha > 0
    # the pass: 3 cm along x from 0.45 m (plus the band), the roller's width along y around y = 0
    cols = np.flatnonzero(mapped.any(axis=0))
    x0, x1 = meta["origin"][0] + cols[0] * 1e-4, meta["origin"][0] + (cols[-1] + 1) * 1e-4
    assert x0 == pytest.approx(0.45 - 0.0035, abs=1e-3) and x1 == pytest.approx(0.48 + 0.0035, abs=1e-3)
    rows = np.flatnonzero(mapped.any(axis=1))
    y_top = meta["origin"][1] + grey.shape[0] * 1e-4 - rows[0] * 1e-4   # row 0 is the top (largest y)
    assert y_top == pytest.approx(0.032, abs=1.5e-3)   # half of the 64 mm the camera sees along the axis
    # the same recording maps to the same file again
    again = tmp_path / "again.png"
    assert main(["map", str(scan_bag), "--out", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()
    # told the latency, it is used as given
    told = tmp_path / "told.png"
    assert main(["map", str(scan_bag), "--out", str(told), "--latency", "0.03"]) == 0
    assert "camera latency given 30.0 ms" in capsys.readouterr().out
    # --strip: the strip map of the same recording, no yaml
    strip = tmp_path / "strip.png"
    assert main(["map", str(scan_bag), "--out", str(strip), "--strip"]) == 0
    assert strip.is_file() and not (tmp_path / "strip.yaml").exists()


def test_a_recording_without_tf_is_the_strip_map(bag_factory, tmp_path):
    rng = np.random.default_rng(0)
    bag = bag_factory([(k * 33_333_333, rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)) for k in range(12)])
    out = tmp_path / "strip.png"
    assert main(["map", str(bag), "--out", str(out)]) == 0
    assert out.is_file() and not (tmp_path / "strip.yaml").exists()


@pytest.mark.slow
def test_the_reader_process_and_the_reader_thread_make_the_same_map(scan_bag, tmp_path, monkeypatch, capsys):
    from touchroller_bringup import forked_reader

    forked = tmp_path / "forked.png"
    assert main(["map", str(scan_bag), "--out", str(forked)]) == 0
    monkeypatch.setattr(forked_reader, "fork_available", lambda: False)   # as on a system without fork
    threaded = tmp_path / "threaded.png"
    assert main(["map", str(scan_bag), "--out", str(threaded)]) == 0
    assert threaded.read_bytes() == forked.read_bytes()
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].split(" -> ")[0] == printed[1].split(" -> ")[0]   # the same frames


@pytest.mark.slow
def test_a_compressed_recording_maps_as_the_raw_one_whatever_the_decoding_workers(scan_bag, tmp_path, capsys):
    # PNG frames in MCAP: decoded up to the band's last row, by a pool of processes or by the reader
    from touchroller_bringup.bag_compression import compress_recording

    compress_recording(scan_bag, tmp_path / "small")
    maps = {}
    for name, bag, extra in (("raw", scan_bag, []), ("one", tmp_path / "small", ["--workers", "1"]),
                             ("three", tmp_path / "small", ["--workers", "3"])):
        assert main(["map", str(bag), "--out", str(tmp_path / name / "map.png"), *extra]) == 0
        maps[name] = [(tmp_path / name / f).read_bytes() for f in ("map.png", "map.tif", "map.yaml")]
    assert maps["one"] == maps["raw"] and maps["three"] == maps["raw"]
    assert main(["map", str(scan_bag), "--out", str(tmp_path / "x.png"), "--workers", "0"]) == 2
    assert "--workers must be in [1, 64]" in capsys.readouterr().err


def test_a_compressed_recording_is_decoded_by_one_worker_per_processor_by_default(scan_bag, tmp_path, monkeypatch):
    """Decoding is the heaviest stage: on two processors two workers share it (the reader and the mapping
    take less than a processor between them), not the reader alone."""
    from touchroller_bringup import decode_pool, forked_reader
    from touchroller_bringup.bag_compression import compress_recording

    compress_recording(scan_bag, tmp_path / "small")
    asked: list[int] = []
    ordered = decode_pool.ordered

    def spy(items, work, wanted, workers, *args, **kwargs):  # type: ignore[no-untyped-def]
        asked.append(workers)
        return ordered(items, work, wanted, 1)   # decoded here: the map is the same

    monkeypatch.setattr(forked_reader, "fork_available", lambda: False)   # the reader in this process
    monkeypatch.setattr(decode_pool, "pool_workers", lambda limit=decode_pool.MAX_WORKERS: 2)
    monkeypatch.setattr(decode_pool, "ordered", spy)
    assert main(["map", str(tmp_path / "small"), "--out", str(tmp_path / "map.png")]) == 0
    assert asked == [2]


def test_frames_of_another_size_than_the_camera_model_are_one_line(tmp_path, capsys):
    """The reader (another process) finds it; the command says it as any other bad input."""
    def records():
        yield TransformRecord("tool0", "touchroller_cylinder", 0, MOUNT.translation, MOUNT.rotation, True)
        for k in range(5):
            yield TransformRecord("base", "tool0", k * 10_000_000, (0.4 + k * 1e-4, 0.0, 0.1), (1.0, 0.0, 0.0, 0.0),
                                  False)
            yield ImageRecord(k * 10_000_000, np.zeros((240, 320, 3), np.uint8))

    bag = tmp_path / "small"
    write_scan(bag, records())
    assert main(["map", str(bag), "--out", str(tmp_path / "m.png")]) == 2
    assert "the camera model is for 640x480 images but the bag has 320x240" in capsys.readouterr().err
    assert gc.get_freeze_count() == 0   # the command froze its set-up objects for the garbage collector; no more


@pytest.mark.slow
def test_world_map_arguments_are_checked(scan_bag, tmp_path, capsys):
    for extra, message in ((["--out", str(tmp_path / "m.jpg")], "is a PNG"),
                           (["--out", str(tmp_path / "m.png"), "--latency", "soon"], "--latency"),
                           (["--out", str(tmp_path / "m.png"), "--metric"], "--strip"),
                           (["--out", str(tmp_path / "m.png"), "--world-frame", "odom"], "no odom")):
        assert main(["map", str(scan_bag), *extra]) == 2
        assert message in capsys.readouterr().err


def test_map_files_are_nav2_maps_written_whole(tmp_path, monkeypatch):
    grey = np.arange(60, dtype=np.uint8).reshape(6, 10)
    alpha = np.where(grey > 20, 255, 0).astype(np.uint8)
    image = WorldMapImage(grey, alpha, 0.001, (0.5, -0.25))
    png, yaml_path = write_world_map(tmp_path / "scan.png", image, "left/base")
    meta = yaml.safe_load(yaml_path.read_text())
    low, high = meta["view"]["stretch"]
    assert {k: meta[k] for k in ("image", "mode", "resolution", "origin", "negate", "occupied_thresh",
                                 "free_thresh", "frame_id")} == \
        {"image": "scan.png", "mode": "scale", "resolution": 0.001, "origin": [0.5, -0.25, 0.0],
         "negate": 0, "occupied_thresh": 1.0, "free_thresh": 0.0, "frame_id": "left/base"}
    assert meta["view"]["downscale"] == 1 and meta["geotiff"]["image"] == "scan.tif"
    assert meta["geotiff"]["size"] == [10, 6] and meta["geotiff"]["origin"] == [0.5, -0.25, 0.0]
    back_grey, back_alpha, back = read_world_map(yaml_path)   # full range, from the GeoTIFF
    assert np.array_equal(back_grey, grey) and np.array_equal(back_alpha, alpha) and back["resolution"] == 0.001
    import PIL.Image

    with PIL.Image.open(png) as picture:
        assert picture.mode == "LA" and picture.size == (10, 6)   # 8-bit grey plus alpha, as nav2 reads it
    unchanged = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)   # another reader: OpenCV's (grey + alpha as BGRA)
    stretched = np.clip(np.floor((grey - low) * 255.0 / (high - low) + 0.5), 0, 255)
    assert np.array_equal(unchanged[..., 0], stretched) and np.array_equal(unchanged[..., 3], alpha)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def broken(*_args, **_kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", broken)
    from touchroller_bringup.errors import UserError

    with pytest.raises(UserError, match="No space left"):
        write_world_map(png, WorldMapImage(grey * 0 + 9, alpha, 0.001, (0.0, 0.0)), "base")
    # the old map stands, all three files of it, and no temporary file is left behind
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert set(before) == {"scan.png", "scan.yaml", "scan.tif"}


def test_an_old_map_png_at_full_resolution_still_reads(tmp_path):
    """A map written before the GeoTIFF (map.png at full resolution, `mode: trinary`) reads as it did."""
    from touchroller_bringup.map_files import png_grey_alpha

    grey = np.arange(60, dtype=np.uint8).reshape(6, 10)
    alpha = np.where(grey > 20, 255, 0).astype(np.uint8)
    (tmp_path / "old.png").write_bytes(png_grey_alpha(grey, alpha))
    (tmp_path / "old.yaml").write_text(yaml.safe_dump({"image": "old.png", "mode": "trinary", "resolution": 0.001,
                                                       "origin": [0.5, -0.25, 0.0], "negate": 0,
                                                       "occupied_thresh": 0.65, "free_thresh": 0.25,
                                                       "frame_id": "base"}))
    back_grey, back_alpha, meta = read_world_map(tmp_path / "old.yaml")
    assert np.array_equal(back_grey, grey) and np.array_equal(back_alpha, alpha) and meta["resolution"] == 0.001


def _small_tf_bag(path, tf, static, hour_late=False):
    """20 noise frames at the default camera size, /tf (base -> tool0) and /tf_static (the mount) as asked."""
    from touchroller_perception.geometry import CameraModel

    camera = CameraModel()
    rng = np.random.default_rng(0)
    shift = 3600_000_000_000 if hour_late else 0
    records = [TransformRecord("tool0", "touchroller_cylinder", 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), True)] \
        if static else []
    for k in range(20):
        stamp = 1_000_000_000 + k * 33_000_000
        if tf:
            records.append(TransformRecord("base", "tool0", stamp + shift, (0.001 * k, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0),
                                           False))
        records.append(ImageRecord(stamp, rng.integers(0, 255, (camera.height, camera.width, 3), np.uint8)))
    write_scan(path, records)
    camera.to_yaml(path.parent / "cal.yaml")
    return path


def test_tf_without_tf_static_says_what_is_missing_and_that_the_world_map_was_skipped(tmp_path, capsys):
    """#28: a recording with /tf but no /tf_static silently gave a strip map."""
    bag = _small_tf_bag(tmp_path / "bag", tf=True, static=False)
    assert main(["map", str(bag), "--params", str(tmp_path / "cal.yaml"), "--out", str(tmp_path / "m.png")]) == 0
    err = capsys.readouterr().err
    assert "has /tf but no /tf_static" in err and "world map was skipped" in err
    assert "tool0 -> touchroller_cylinder" in err


@pytest.mark.parametrize("case, message", [
    ("hour", "base -> tool0 is known over"),
    ("resolution", "--resolution 1e-06 m per pixel"),
    ("empty_frame", "--world-frame must not be empty"),
])
def test_a_map_that_cannot_be_placed_says_why_in_one_line(tmp_path, capsys, case, message):
    """#28: TF an hour after the images and --resolution 1e-6 ended in 'TypeError: unsupported operand type(s)
    for *: NoneType and int' (cv2.flip of an empty map); an empty frame id in a raw ValueError."""
    bag = _small_tf_bag(tmp_path / "bag", tf=True, static=True, hour_late=case == "hour")
    extra = {"resolution": ["--resolution", "1e-6"], "empty_frame": ["--world-frame", ""]}.get(case, [])
    out = tmp_path / "m.png"
    assert main(["map", str(bag), "--params", str(tmp_path / "cal.yaml"), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err and "TypeError" not in err and "ValueError" not in err, err
    assert not out.exists()


BLEND_AREA = (0.42, -0.045, 0.05, 0.09)   # 5 x 9 cm: two passes


def _record(path, sensor, plan, latency, **options):
    assert write_scan(path, sim_scans.bag_records(sim_scans.sweep(sensor, plan, latency, **options))) > 100
    return path


def _in_place_ssim(sensor, yaml_path, area) -> tuple[float, float]:
    """(SSIM of the written map against the true surface where the map says it lies, over `area`;
    the fraction of `area` mapped)."""
    from touchroller_driver.sim.camera import surface_frame
    from touchroller_perception.metrics import ssim

    grey, alpha, meta = read_world_map(yaml_path)
    grey, alpha = grey[::-1].astype(np.float32), alpha[::-1]   # rows growing with y
    res = meta["resolution"]
    _, truth = sensor.world_truth(surface_frame(sensor.scene), tuple(meta["origin"][:2]), grey.shape, res)
    c0, r0 = (int(round((area[k] - meta["origin"][k]) / res)) for k in (0, 1))
    c1, r1 = c0 + int(round(area[2] / res)), r0 + int(round(area[3] / res))
    a, b = grey[r0:r1, c0:c1], truth[r0:r1, c0:c1].astype(np.float32)
    covered = float((alpha[r0:r1, c0:c1] > 0).mean())
    return ssim(*(np.clip((x - x.mean()) / x.std() * 40 + 128, 0, 255) for x in (a, b))), covered


@pytest.mark.slow
def test_a_blended_raster_with_an_untold_latency_is_placed_in_place(tmp_path, capsys):
    """Touchdown and lift-off at speed (no start or stop in contact), 35 ms late, the mapper not told:
    the opposite passes give the latency, and the map lies where the surface is."""
    sensor = sim_scans.large_surface(seed=0)
    plan = sim_scans.raster(BLEND_AREA, approach_speed=None, profile="blend")
    bag = _record(tmp_path / "bag", sensor, plan, 0.035, jitter=0.01)
    out = tmp_path / "map.png"
    assert main(["map", str(bag), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "camera latency estimated " in printed.out, printed
    estimated = float(printed.out.split("camera latency estimated ")[1].split(" ms")[0])
    assert estimated == pytest.approx(35.0, abs=3.0)
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert meta["camera_latency"]["observable"] and "opposite_passes" in meta["camera_latency"]["sources"]
    assert 0 < meta["camera_latency"]["sigma_ms"] < 3.0
    score, covered = _in_place_ssim(sensor, tmp_path / "map.yaml", BLEND_AREA)
    assert covered > 0.98 and score >= 0.90
    # the same recording placed by TF with no latency: the passes 0.7 mm off each way, the map not in place
    zero = tmp_path / "zero.png"
    assert main(["map", str(bag), "--out", str(zero), "--latency", "0", "--no-register"]) == 0
    assert _in_place_ssim(sensor, tmp_path / "zero.yaml", BLEND_AREA)[0] < score - 0.3


@pytest.mark.slow
def test_one_pass_at_constant_speed_warns_and_keeps_the_configured_latency(tmp_path, capsys):
    """Nothing in one pass rolled at constant speed, touching down and lifting off at speed, pins the
    latency down: the map says so and uses the configured one, never a guess as an estimate."""
    sensor = sim_scans.large_surface(seed=2)
    plan = sim_scans.raster([0.45, -0.02, 0.04, 0.04], approach_speed=None, profile="constant")
    bag = _record(tmp_path / "bag", sensor, plan, 0.05)
    out = tmp_path / "map.png"
    assert main(["map", str(bag), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "camera latency not observable" in printed.out and "configured 0.0 ms used" in printed.out, printed
    assert "WARN: camera latency not observable" in printed.err
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert meta["camera_latency"]["observable"] is False and meta["camera_latency"]["value_ms"] == 0.0


def test_with_a_photometric_model_the_height_map_lies_beside_the_map_in_place(scan_bag, tmp_path, capsys):
    from touchroller_bringup.map_files import read_height_tif
    from touchroller_driver.sim.camera import surface_frame
    from touchroller_driver.sim.photometric import sim_photometric

    sensor = sim_scans.large_surface(seed=1)
    photometric = sim_photometric(sensor)   # its presses spread over the band: 6 leave most of it unlearnt
    model, reference = tmp_path / "photometric.npz", tmp_path / "reference.png"
    photometric.calibration.model.save(model)
    cv2.imwrite(str(reference), photometric.reference)
    out = tmp_path / "map.png"
    assert main(["map", str(scan_bag), "--out", str(out), "--latency", "0.03", "--photometric", str(model),
                 "--reference", str(reference)]) == 0
    assert "height.tif" in capsys.readouterr().out
    height, (x0, y_top), resolution = read_height_tif(tmp_path / "height.tif")
    grey, alpha, meta = read_world_map(tmp_path / "map.yaml")
    assert height.dtype == np.float32 and height.shape == grey.shape and resolution == meta["resolution"]
    assert x0 == pytest.approx(meta["origin"][0]) and y_top == pytest.approx(meta["origin"][1] + grey.shape[0] * 1e-4)
    known = np.isfinite(height)
    assert known.sum() > 0.5 * (alpha > 0).sum() and not (known & (alpha == 0)).any()
    # in place against the true relief (rows growing with y for the truth)
    truth, _ = sensor.world_truth(surface_frame(sensor.scene), (x0, y_top - grey.shape[0] * 1e-4), grey.shape, 1e-4)
    mine, true = height[::-1][known[::-1]], truth[known[::-1]]
    assert np.corrcoef(mine, true)[0, 1] > 0.4   # one pass, its ends included (misplaced: ~0)
    # the arguments go together
    assert main(["map", str(scan_bag), "--out", str(tmp_path / "m2.png"), "--photometric", str(model)]) == 2
    assert "go together" in capsys.readouterr().err
