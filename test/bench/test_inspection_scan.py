"""The inspection bench's scan helpers on data made here: the line spread of a blurred crack, the live
latency from watched poses and findings, and the square metre's arithmetic."""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import tifffile

from bench.inspection_scan import PAPER_AREA_M2, PAPER_S, Watch, line_spread, live_latency, square_metre
from touchroller_perception.inspection import Finding

RES = 1e-4


def _height_tif(path, width_m, depth_m, blur_m, rows=200, cols=300):
    yy, xx = np.mgrid[0:rows, 0:cols]
    y = (rows - yy - 0.5) * RES
    h = -(depth_m * np.exp(-4 * math.log(2) * ((y - 0.010) / width_m) ** 2))        # a groove along x at y 10 mm
    sigma = blur_m / RES / (2 * math.sqrt(2 * math.log(2)))
    h = cv2.GaussianBlur(h.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    tifffile.imwrite(path, h, extratags=[(33550, 12, 3, (RES, RES, 0.0), False),
                                         (33922, 12, 6, (0.0, 0.0, 0.0, 0.0, rows * RES, 0.0), False)])


def test_the_line_spread_of_a_blurred_crack_is_its_blur_and_keeps_its_cross_section(tmp_path):
    _height_tif(tmp_path / "height.tif", 0.2e-3, 50e-6, 0.4e-3)
    truth = [Finding(1, "crack", 0.015, 0.010, 0.02, 0.2e-3, 50e-6, 4e-6, 1.0, polylines=(((0.005, 0.010),
                                                                                            (0.025, 0.010)),))]
    (spread,) = line_spread(tmp_path / "height.tif", truth)
    assert spread.blur_fwhm_mm == pytest.approx(0.4, abs=0.03)
    assert spread.map_fwhm_mm == pytest.approx(math.hypot(0.2, 0.4), abs=0.03)
    assert spread.area_ratio == pytest.approx(1.0, abs=0.05)


def _crack_map(path, width_m, depth_m, total_fwhm_m, angle_deg, rows=200, cols=300):
    """A straight groove through the map's middle at `angle_deg` to x (so its centre falls at every phase of the
    grid along it), its cross-section a Gaussian of FWHM `total_fwhm_m` (a crack of FWHM `width_m` blurred: its
    area kept), sampled at the cell centres; and the truth's crack along it."""
    yy, xx = np.mgrid[0:rows, 0:cols]
    x, y = (xx + 0.5) * RES, (rows - yy - 0.5) * RES
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    centre = np.array([cols / 2 * RES, rows / 2 * RES])
    distance = -(x - centre[0]) * s + (y - centre[1]) * c
    h = -(depth_m * width_m / total_fwhm_m) * np.exp(-4 * math.log(2) * (distance / total_fwhm_m) ** 2)
    tifffile.imwrite(path, h.astype(np.float32), extratags=[(33550, 12, 3, (RES, RES, 0.0), False),
                                                            (33922, 12, 6, (0.0, 0.0, 0.0, 0.0, rows * RES, 0.0),
                                                             False)])
    ends = tuple(tuple(centre + t * np.array([c, s])) for t in (-0.008, 0.008))
    return h.astype(np.float32), Finding(1, "crack", *centre, 0.016, width_m, depth_m, 0.0, 1.0, polylines=(ends,))


@pytest.mark.parametrize("blur_mm", [0.37, 0.40, 0.42])
def test_the_blur_calibrated_off_reference_cracks_makes_the_detector_read_other_cracks_width_and_depth(
        tmp_path, blur_mm):
    # the detector takes a crack's width as sqrt(M² - p² - b²) (M its profiles' FWHM, p its map's pixel, b the
    # declared blur) and its depth as the cross-section's area over that width: at a width of 0.4 b, 0.01 mm of
    # blur is some 20 % of depth, so the line spread must measure the FWHM the detector measures and leave its
    # pixel out of the blur. Calibrated on two reference cracks, read on three others (other widths, angles).
    from touchroller_perception.inspection import InspectionConfig, inspect

    config = InspectionConfig()
    pixel_mm = config.footprint_fwhm_px * RES * 1e3

    def crack(width_mm, angle):
        total = math.sqrt(width_mm**2 + pixel_mm**2 + blur_mm**2) * 1e-3
        return _crack_map(tmp_path / "height.tif", width_mm * 1e-3, 50e-6, total, angle)

    blurs = []
    for width_mm, angle in ((0.17, 3.0), (0.36, -7.0)):
        _, truth = crack(width_mm, angle)
        (spread,) = line_spread(tmp_path / "height.tif", [truth])
        blurs.append(spread.blur_fwhm_mm)
    declared = replace(config, blur_fwhm_m=float(np.median(blurs)) * 1e-3)
    for width_mm, angle in ((0.16, 5.0), (0.16, -11.0), (0.29, 2.0)):
        h, truth = crack(width_mm, angle)
        (found,) = [f for f in inspect(h, RES, (0.0, 0.0), config=declared).findings if f.kind == "crack"]
        assert found.width_m * 1e3 == pytest.approx(width_mm, abs=0.01)
        assert found.depth_m == pytest.approx(50e-6, rel=0.08)

def _dent(x):
    ring = tuple((x + 5e-4 * math.cos(a), 5e-4 * math.sin(a)) for a in np.linspace(0, 2 * math.pi, 17))
    return Finding(1, "dent", x, 0.0, 1e-3, 1e-3, 40e-6, 8e-7, 1.0, polygon=ring)


def test_the_live_latency_runs_from_the_last_frame_reaching_a_defect_to_the_first_message_showing_it():
    watch = Watch()
    watch.poses = [(0.0, 0, 0.40, 0.0, 0.2)]                               # above the start: not pressed
    watch.poses += [(1.0 + 0.1 * k, (1 + k) * 10**8, 0.40 + 0.003 * 0.1 * k, 0.0, 0.1) for k in range(101)]
    # the band reaches 3 mm either side of the contact line: the map spans the roll and 3 mm more each way
    extent = (0.397, -0.01, 0.433, 0.01)
    shown_at = 6.2                                                         # wall, and stamp 5.5 s
    # each shape with the kind its label names: a crack's marker on the dent does not show the dent
    watch.findings = [(shown_at - 1.0, 45 * 10**8, [("crack", np.array([[0.409, 0.0], [0.411, 0.0]]))]),
                      (shown_at, 55 * 10**8, [("dent", np.array([[0.410, 0.0]]))])]
    latency = live_latency(watch, [_dent(0.410), _dent(0.420)], extent)
    # the band's trailing edge leaves x = 0.4105 when the contact line is at 0.4135: 4.5 s into the roll
    assert latency[0].wall_s == pytest.approx(shown_at - 5.5, abs=0.11)
    assert latency[0].sim_s == pytest.approx(5.5 - 4.6, abs=0.11)
    assert not latency[0].final
    assert math.isnan(latency[1].wall_s)                                   # never shown


def test_a_square_metre_is_the_plan_plus_what_mapping_and_inspection_add():
    watch = Watch()
    watch.poses = [(k, k * 10**9, 0.40 + 0.011 * k, 0.0, 0.1) for k in range(10)]
    fast = square_metre(watch, map_ms_per_frame=1.0, map_frames=100, megapixels_per_s=10.0)
    assert fast.passes == 22 and fast.measured_speed_m_s == pytest.approx(0.011)
    assert fast.rolling_s == pytest.approx(22 * 1.0 / 0.011, rel=0.02) and fast.arm_s > fast.rolling_s
    assert fast.total_s == pytest.approx(fast.arm_s + 10.0)                # mapping keeps up: inspection only
    slow = square_metre(watch, map_ms_per_frame=50.0, map_frames=100, megapixels_per_s=10.0)
    assert slow.total_s == pytest.approx(slow.arm_s + slow.map_cpu_s - slow.rolling_s + 10.0)
    assert fast.paper_s == pytest.approx(PAPER_S / PAPER_AREA_M2)
