"""The inspection detector on small height maps made here: what it finds, what it must not report, and
the hard inputs (NaN, constant, tiny, defects at the edge)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from touchroller_perception.inspection import InspectionConfig, inspect, inspect_height, inspect_region, parse_wkt

RES = 1e-4


def surface(shape=(300, 400), noise=0.5e-6, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.normal(0, noise, shape) + 20e-3).astype(np.float32)   # a panel 20 mm above the base plane


def carve_line(h, p0, p1, width_m, depth_m):
    """A straight Gaussian groove from p0 to p1 ((x, y) metres, map frame) of FWHM width_m."""
    rows, cols = h.shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    x, y = (xx + 0.5) * RES, (rows - yy - 0.5) * RES
    a, b = np.array(p0), np.array(p1)
    d = b - a
    t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / (d @ d), 0, 1)
    dist = np.hypot(x - (a[0] + t * d[0]), y - (a[1] + t * d[1]))
    h -= (depth_m * np.exp(-4 * math.log(2) * (dist / width_m) ** 2)).astype(np.float32)


def carve_blob(h, centre, diameter, depth):
    rows, cols = h.shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    r = np.hypot((xx + 0.5) * RES - centre[0], (rows - yy - 0.5) * RES - centre[1])
    h -= (depth * np.where(r < diameter / 2, 0.5 * (1 + np.cos(np.pi * r / (diameter / 2))), 0)).astype(np.float32)


def test_a_crack_is_found_where_it_is_and_measured():
    h = surface()
    carve_line(h, (0.008, 0.010), (0.030, 0.020), 0.3e-3, 50e-6)
    found = inspect_height(h, RES, (0.0, 0.0))
    assert [f.kind for f in found] == ["crack"]
    crack = found[0]
    true_length = math.hypot(0.022, 0.010)
    assert crack.length_m == pytest.approx(true_length, rel=0.05)
    assert crack.width_m == pytest.approx(0.3e-3, abs=0.05e-3)
    assert crack.depth_m == pytest.approx(50e-6, rel=0.15)
    assert (crack.x, crack.y) == pytest.approx((0.019, 0.015), abs=2e-4)
    kind, parts = parse_wkt(crack.wkt)
    assert kind == "LINESTRING" and len(parts) == 1
    # every vertex of the centreline lies on the true line (within a pixel)
    p = np.array(parts[0])
    d = np.abs((p[:, 0] - 0.008) * 0.010 - (p[:, 1] - 0.010) * 0.022) / true_length
    assert d.max() < 1e-4


def test_a_branched_crack_is_one_multilinestring():
    h = surface()
    carve_line(h, (0.005, 0.015), (0.035, 0.015), 0.3e-3, 60e-6)
    carve_line(h, (0.020, 0.015), (0.028, 0.025), 0.25e-3, 50e-6)
    found = inspect_height(h, RES, (0.0, 0.0))
    assert [f.kind for f in found] == ["crack"]
    kind, parts = parse_wkt(found[0].wkt)
    assert kind == "MULTILINESTRING" and len(parts) == 2
    assert found[0].length_m == pytest.approx(0.030, rel=0.06)     # the trunk


def test_dents_and_bumps_with_signed_depth():
    h = surface()
    carve_blob(h, (0.010, 0.015), 2e-3, 40e-6)
    carve_blob(h, (0.030, 0.015), 2e-3, -40e-6)
    found = sorted(inspect_height(h, RES, (0.0, 0.0)), key=lambda f: f.x)
    assert [f.kind for f in found] == ["dent", "bump"]
    assert found[0].depth_m == pytest.approx(40e-6, rel=0.1)
    assert found[1].depth_m == pytest.approx(-40e-6, rel=0.1)
    for f, x in zip(found, (0.010, 0.030), strict=True):
        assert (f.x, f.y) == pytest.approx((x, 0.015), abs=1e-4)
        kind, parts = parse_wkt(f.wkt)
        assert kind == "POLYGON" and parts[0][0] == parts[0][-1]
        assert f.length_m == pytest.approx(1e-3, rel=0.25)       # half-depth diameter of the raised cosine


def test_texture_shallower_than_the_threshold_is_not_reported():
    h = surface(noise=1e-6)
    for k in range(20):                                  # brushing: long shallow parallel scratches
        carve_line(h, (0.002, 0.002 + k * 1.3e-3), (0.038, 0.002 + k * 1.3e-3), 0.08e-3, 4e-6)
    assert inspect_height(h, RES, (0.0, 0.0)) == []
    carve_line(h, (0.010, 0.004), (0.020, 0.026), 0.2e-3, 30e-6)   # a real crack across them is
    assert [f.kind for f in inspect_height(h, RES, (0.0, 0.0))] == ["crack"]


def test_a_masked_panel_joint_is_silenced():
    h = surface()
    carve_line(h, (0.020, -0.01), (0.020, 0.05), 0.6e-3, 150e-6)
    assert [f.kind for f in inspect_height(h, RES, (0.0, 0.0))] == ["crack"]     # unmasked: reported
    cols = (np.arange(h.shape[1]) + 0.5) * RES
    mask = np.broadcast_to(np.abs(cols - 0.020) < 1.5e-3, h.shape)
    assert inspect_height(h, RES, (0.0, 0.0), mask=mask) == []


def test_unmapped_areas_and_map_edges_are_not_findings():
    h = surface()
    h[:, :150] += np.float32(40e-6)                 # a step where the unmapped area begins ...
    h[:, 140:160] = np.nan                          # ... and a gap
    h[:40] = np.nan
    result = inspect(h, RES, (0.0, 0.0))
    assert result.findings == []
    assert result.diagnostics.valid_pixels > 0


def test_a_map_whose_first_rows_curl_up_reports_no_ridge_along_its_edge():
    # a height map's first and last columns of a roll curl (the band's outer rows alone see them): a ridge
    # along the edge, 15 um over 1.5 mm, is the edge's, not a bump; a dent and a crack beside it still are
    h = surface()
    cols = (np.arange(h.shape[1]) + 0.5) * RES
    h += (15e-6 * np.exp(-cols / 1.5e-3) + 15e-6 * np.exp(-(0.040 - cols) / 1.5e-3)).astype(np.float32)[None, :]
    carve_blob(h, (0.004, 0.015), 2e-3, 40e-6)
    carve_line(h, (0.001, 0.005), (0.015, 0.006), 0.3e-3, 50e-6)   # from the edge inwards: kept
    result = inspect(h, RES, (0.0, 0.0))
    assert sorted(f.kind for f in result.findings) == ["crack", "dent"]
    assert result.diagnostics.dropped_edge >= 1
    assert [f.kind for f in inspect(h, RES, (0.0, 0.0), config=InspectionConfig(edge_band_m=0)).findings
            ].count("bump") >= 1                                    # without the rule the ridges are bumps


def blurred(h, fwhm_m):
    import cv2

    sigma = fwhm_m / RES / (2 * math.sqrt(2 * math.log(2)))
    return cv2.GaussianBlur(h, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def test_a_map_blurred_by_its_sensor_gives_true_widths_and_depths_when_the_blur_is_declared():
    # a sensor's gel blurs a 0.3 mm crack to 0.5 mm, 30 um deep: its width and depth come back with blur_fwhm_m
    h = surface(noise=0.1e-6)
    carve_line(h, (0.008, 0.010), (0.030, 0.020), 0.3e-3, 50e-6)
    carve_blob(h, (0.010, 0.022), 2e-3, 40e-6)
    blur = 0.4e-3
    h = blurred(h, blur)
    plain = {f.kind: f for f in inspect_height(h, RES, (0.0, 0.0))}
    assert plain["crack"].width_m > 0.45e-3 and plain["crack"].depth_m < 35e-6      # what the blur does
    found = {f.kind: f for f in inspect_height(h, RES, (0.0, 0.0), config=InspectionConfig(blur_fwhm_m=blur))}
    assert found["crack"].width_m == pytest.approx(0.3e-3, abs=0.04e-3)
    assert found["crack"].depth_m == pytest.approx(50e-6, rel=0.15)
    assert found["dent"].depth_m == pytest.approx(40e-6, rel=0.15)
    assert abs(found["dent"].depth_m - 40e-6) < abs(plain["dent"].depth_m - 40e-6)
    assert found["crack"].confidence == pytest.approx(plain["crack"].confidence)


def test_a_crack_across_a_pass_seam_is_one_crack():
    h = surface()
    h[150:] += np.float32(3e-6)                     # the second pass sits 3 um higher
    carve_line(h, (0.020, 0.005), (0.022, 0.025), 0.2e-3, 30e-6)
    found = inspect_height(h, RES, (0.0, 0.0))
    assert [f.kind for f in found] == ["crack"]
    assert found[0].length_m == pytest.approx(math.hypot(0.002, 0.020), rel=0.06)


def test_coordinates_follow_the_origin_and_rows_run_down():
    h = surface()
    carve_blob(h, (0.010, 0.025), 2e-3, 40e-6)      # near the top of the map: small row numbers
    (f,) = inspect_height(h, RES, (1.0, -2.0))
    assert (f.x, f.y) == pytest.approx((1.010, -1.975), abs=1e-4)


def test_a_region_of_the_map_gives_the_whole_map_findings_inside_it():
    h = surface(shape=(300, 600))
    carve_blob(h, (0.010, 0.015), 2e-3, 40e-6)
    carve_blob(h, (0.050, 0.015), 2e-3, 40e-6)
    whole = inspect_height(h, RES, (0.0, 0.0))
    part = inspect_region(h, RES, (0.0, 0.0), (0.040, 0.0, 0.060, 0.030)).findings
    assert len(whole) == 2 and len(part) == 1
    assert (part[0].x, part[0].y, part[0].depth_m) == pytest.approx((whole[1].x, whole[1].y, whole[1].depth_m),
                                                                    rel=1e-3, abs=2e-5)


def test_a_dent_cut_by_the_map_edge_is_inside_the_map():
    h = surface()
    carve_blob(h, (0.0005, 0.015), 3e-3, 60e-6)
    for f in inspect_height(h, RES, (0.0, 0.0)):
        assert 0 <= f.x <= 0.040 and 0 <= f.y <= 0.030


def test_bad_configuration_and_input_are_one_clear_error():
    with pytest.raises(ValueError, match="low_fraction"):
        InspectionConfig(low_fraction=0)
    with pytest.raises(ValueError, match="noise_multiple"):
        InspectionConfig(noise_multiple=float("nan"))
    with pytest.raises(ValueError, match="2-D"):
        inspect(np.zeros(5), RES, (0, 0))
    with pytest.raises(ValueError, match="resolution"):
        inspect(np.zeros((5, 5)), 0.0, (0, 0))
    with pytest.raises(ValueError, match="mask"):
        inspect(np.zeros((5, 5)), RES, (0, 0), mask=np.zeros((4, 4), bool))


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 40), cols=st.integers(1, 40), fill=st.sampled_from(["nan", "constant", "noise", "mixed"]),
       seed=st.integers(0, 2**16))
def test_hard_inputs_never_fail_and_stay_inside_the_map(rows, cols, fill, seed):
    rng = np.random.default_rng(seed)
    if fill == "nan":
        h = np.full((rows, cols), np.nan, np.float32)
    elif fill == "constant":
        h = np.full((rows, cols), 0.01, np.float32)
    else:
        h = rng.normal(0, 20e-6, (rows, cols)).astype(np.float32)
        if fill == "mixed":
            h[rng.random((rows, cols)) < 0.3] = np.nan
            h[rng.random((rows, cols)) < 0.05] = np.inf
    result = inspect(h, RES, (0.0, 0.0))
    if fill in ("nan", "constant"):
        assert result.findings == []
    for f in result.findings:
        assert 0 <= f.x <= cols * RES and 0 <= f.y <= rows * RES
        assert f.kind in ("crack", "dent", "bump") and 0 <= f.confidence <= 1
        parse_wkt(f.wkt)


def shaded(h):
    """A tactile map's grey: shading by the slopes along one light direction (a defect's bright and dark
    sides), 128 on the flat, plus a little noise."""
    gy, gx = np.gradient(h.astype(np.float64), RES)
    rng = np.random.default_rng(3)
    return (128 + 400 * (0.8 * gx + 0.6 * gy) + rng.normal(0, 0.3, h.shape)).astype(np.float32)


def test_an_intensity_map_shows_each_defect_once_where_it_is_without_a_depth():
    """Shading draws a crack as a bright and a dark line and a dent as two half-moons: each is one
    finding in its place (before the unsigned anomaly, each crack came out as two)."""
    from touchroller_perception.inspection import inspect_intensity

    h = surface(noise=0.0)
    carve_line(h, (0.006, 0.008), (0.030, 0.012), 0.25e-3, 50e-6)
    carve_blob(h, (0.012, 0.022), 2e-3, 40e-6)
    carve_blob(h, (0.030, 0.022), 2e-3, -40e-6)
    found = inspect_intensity(shaded(h), RES, (0.0, 0.0)).findings
    cracks = [f for f in found if f.kind == "crack"]
    compact = sorted((f for f in found if f.kind != "crack"), key=lambda f: f.x)
    assert len(cracks) == 1 and len(compact) == 2, found
    # on the true line (the shading's two sides joined about it); along it the ends decide the centroid
    p = np.array(cracks[0].polylines[0])
    assert (np.abs((p[:, 0] - 0.006) * 0.004 - (p[:, 1] - 0.008) * 0.024) / math.hypot(0.024, 0.004)).max() < 3e-4
    assert (cracks[0].x, cracks[0].y) == pytest.approx((0.018, 0.010), abs=6e-4)
    assert cracks[0].length_m == pytest.approx(math.hypot(0.024, 0.004), rel=0.1)
    assert [(f.x, f.y) for f in compact] == [pytest.approx((0.012, 0.022), abs=3e-4),
                                              pytest.approx((0.030, 0.022), abs=3e-4)]
    assert all(math.isnan(f.depth_m) for f in found)
    # the same through a window of the map (the live node's way)
    window = inspect_region(shaded(h), RES, (0.0, 0.0), (0.0, 0.0, 0.04, 0.016), intensity=True).findings
    assert [f.kind for f in window] == ["crack"] and window[0].x == pytest.approx(cracks[0].x, abs=1e-4)
