"""A simulated sensor's photometric model made on the fly, and the relief it gives a world mapper's band."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

import touchroller_driver.sim as sim
from touchroller_driver.sim.photometric import sim_photometric
from touchroller_perception.world_height import HeightSource, WorldHeightConfig
from touchroller_perception.world_map import WorldMapConfig, WorldMapper


@pytest.fixture(scope="module")
def grained():
    sensor = sim.SimulatedSensor(sim.load_scene("large_surface"), seed=0)
    return sensor, sim_photometric(sensor, presses=6)


def test_the_band_relief_follows_the_true_indentation(grained):
    sensor, photometric = grained
    assert photometric.reference.shape == (sensor.camera.height, sensor.camera.width, 3)
    mapper = WorldMapper(sensor.camera, lambda stamps: np.full((len(stamps), 4, 4), np.nan), WorldMapConfig(),
                         height=HeightSource(photometric.calibration.model, photometric.reference))
    layers = sensor.render_layers(sim.RollerState(travel=0.1, depth=5e-4))
    band = mapper.height_band(layers["image"])
    assert band is not None and band.relief.shape == mapper.band_shape and band.contact.all()
    # the truth on the band: the renderer's indentation resampled as the band is, plus the cylinder
    maker = mapper._band_heights
    assert maker is not None

    v0, v1 = maker.rows
    truth = cv2.remap(layers["indentation"][v0:v1].astype(np.float32), *maker.maps, cv2.INTER_LINEAR) + maker.cylinder
    # one frame's slow errors (the press's profile read a little flat, each column's sum across the band)
    # differ from frame to frame or are the same at every place and average out in the map; its fine relief
    # (what varies within 1 mm) is compared here
    def fine(a: np.ndarray) -> np.ndarray:
        return (a - cv2.GaussianBlur(a, (0, 0), 10.0))[:, 20:-20]

    assert np.corrcoef(fine(band.relief).ravel(), fine(truth).ravel())[0, 1] > 0.8
    assert float(np.std(fine(band.relief) - fine(truth))) < 0.6 * float(np.std(fine(truth)))


def _fine_relief(grained, config: WorldHeightConfig, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A grained frame's band relief as the map reads it with `config`, and the true relief there (the
    indentation on the band's grid plus the cylinder), each less its Gaussian of `sigma` px (its fine relief)."""
    sensor, photometric = grained
    layers = sensor.render_layers(sim.RollerState(travel=0.1, depth=5e-4))
    mapper = WorldMapper(sensor.camera, lambda stamps: np.full((len(stamps), 4, 4), np.nan), WorldMapConfig(),
                         height=HeightSource(photometric.calibration.model, photometric.reference, config))
    band = mapper.height_band(layers["image"])
    maker = mapper._band_heights
    assert band is not None and maker is not None
    v0, v1 = maker.rows
    truth = cv2.remap(layers["indentation"][v0:v1].astype(np.float32), *maker.maps, cv2.INTER_LINEAR)
    truth += maker.cylinder
    read, true = ((a - cv2.GaussianBlur(a, (0, 0), sigma))[:, 20:-20].ravel() for a in (band.relief, truth))
    return read, true


def test_the_map_reads_a_frame_with_less_smoothing_than_the_model_was_calibrated_with(grained):
    """The model is calibrated with the image smoothed by 1 px (`MAP_CALIBRATION`); the map reads its frames
    with 0.5 px (`WorldHeightConfig.smoothing`) and keeps more of the relief a few pixels across: its fine
    relief (what departs from a 3 px Gaussian) reads nearer its true size than read with the model's own."""
    _, photometric = grained
    assert photometric.calibration.model.config.smoothing == 1.0
    gains = []
    for config in (WorldHeightConfig(), WorldHeightConfig(smoothing=None)):
        read, true = _fine_relief(grained, config, 3.0)
        gains.append(float(read @ true / (true @ true)))
        assert np.corrcoef(read, true)[0, 1] > 0.95
    assert WorldHeightConfig().smoothing == 0.5
    assert gains[0] > gains[1] + 0.08 and gains[0] > 0.8


def test_the_map_integrates_a_frames_slopes_as_the_pixels_footprints_and_keeps_more_of_its_fine_relief(grained):
    """Read as each pixel's mean slope over its footprint (`WorldHeightConfig.slopes`, the default), a frame's
    fine relief (what departs from a 1.5 px Gaussian) reads nearer its true size than read as the slopes at the
    pixel centres, and follows it as well."""
    gains = []
    for config in (WorldHeightConfig(), WorldHeightConfig(slopes="centre")):
        read, true = _fine_relief(grained, config, 1.5)
        gains.append(float(read @ true / (true @ true)))
        assert np.corrcoef(read, true)[0, 1] > 0.98
    assert WorldHeightConfig().slopes == "footprint"
    assert gains[0] > gains[1] + 0.03


def test_rows_cut_from_the_frame_give_the_same_relief(grained):
    sensor, photometric = grained
    mapper = WorldMapper(sensor.camera, lambda stamps: np.full((len(stamps), 4, 4), np.nan), WorldMapConfig(),
                         height=HeightSource(photometric.calibration.model, photometric.reference))
    image = sensor.render(sim.RollerState(travel=0.05, depth=5e-4))
    rows = mapper.height_rows(image.shape[:2])
    assert rows is not None
    whole = mapper.height_band(image)
    cut = mapper.height_band(image[rows[0]:rows[1]], rows[0], image.shape[0])
    assert whole is not None and cut is not None and np.array_equal(whole.relief, cut.relief)


def test_without_a_photometric_model_there_is_no_height():
    sensor = sim.SimulatedSensor(sim.load_scene("large_surface"), seed=0)
    mapper = WorldMapper(sensor.camera, lambda stamps: np.full((len(stamps), 4, 4), np.nan), WorldMapConfig())
    assert mapper.height_band(np.zeros((480, 640, 3), np.uint8)) is None and mapper.height_layer() is None
    assert set(mapper.canvas.store.layers) == {"band", "flat", "weight"}   # no height layers


def test_the_model_reads_the_contact_bands_slopes_off_the_contact_line():
    # the presses land over the rows the world height integrates, not only near the contact line: a slope of the
    # pressed band a few millimetres off that line (where the tube's curvature makes it steep) reads its size
    # (pressed within 0.04 rad of the line only, as the ball_presses scene does: 0.92 of the renderer's slopes)
    sensor = sim.SimulatedSensor(sim.load_scene("inspection_panel"), seed=0)
    photometric = sim_photometric(sensor)
    layers = sensor.render_layers(sim.RollerState(travel=0.05, depth=5e-4))
    indentation = layers["indentation"]
    gy_true = cv2.Sobel(indentation, cv2.CV_32F, 0, 1, ksize=3) * sensor._sobel_kv   # the renderer's own slopes
    _, gy = photometric.calibration.model.slopes(layers["image"], photometric.reference)
    inside = cv2.erode((indentation > 1e-5).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    steep = inside & (np.abs(gy_true) > 0.1)
    assert steep.sum() > 10000
    gain = float((gy[steep] * gy_true[steep]).sum() / (gy_true[steep] ** 2).sum())
    assert 0.945 < gain < 1.05


def test_the_presses_band_depth_is_checked():
    sensor = sim.SimulatedSensor(sim.load_scene("inspection_panel"), seed=0)
    with pytest.raises(ValueError, match="band_depth"):
        sim_photometric(sensor, band_depth=float("nan"))


def test_every_press_lands_in_view_and_the_position_degree_is_chosen(grained):
    # the presses are spread over the part of the roller the camera sees (the scene's 0.8 of its length
    # reaches beyond the image's ends, and a press there is lost), and the map's calibration weighs the
    # position degree on held-out presses
    _, photometric = grained
    calibration = photometric.calibration
    assert len(calibration.presses) == 6
    assert {s.degree for s in calibration.degree_scores} == {0, 1, 2, 3}
    chosen = min(calibration.degree_scores, key=lambda s: (s.gain_deviation, s.degree)).degree
    assert calibration.model.config.position_degree == chosen


def test_the_calibration_presses_land_in_view_over_the_band():
    # the scene's own 0.8 of the roller's length reaches beyond the image's ends: there a press is lost (a third
    # of them, before); the presses now spread over what the camera sees, evenly across the band's rows
    from touchroller_driver.sim.photometric import ball_press_scene

    sensor = sim.SimulatedSensor(sim.load_scene("large_surface"), seed=0)
    scene = ball_press_scene(sensor, presses=24)
    cam = sensor.camera
    contacts = [f.truth["contacts"][0] for f in sim.SimulatedSensor(scene, seed=1).frames()
                if f.truth["phase"] == "press"]
    pixels = np.array([c["pixel"] for c in contacts])
    assert len(pixels) == 24
    assert ((pixels[:, 0] >= 0) & (pixels[:, 0] < cam.width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < cam.height)).all()
    alphas = np.array([c["alpha"] for c in contacts])
    span = float(scene.motion["alpha_span"])
    assert np.histogram(alphas, bins=3, range=(-span, span))[0].min() == 8
