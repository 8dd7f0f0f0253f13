"""Scene files and the scene loader."""
import pytest

from touchroller_driver.sim import available_scenes, load_scene


def test_all_scenes_load_and_render(tmp_path):
    names = available_scenes()
    for required in ("surface_mapping", "contact_localisation", "calibration_chessboard",
                     "calibration_hemispheres", "flat_sensor_comparison"):
        assert required in names
    for variant in ("slow", "medium", "fast"):
        scene = load_scene("surface_mapping", variant=variant)
        assert scene.duration == {"slow": 15.0, "medium": 10.0, "fast": 5.0}[variant]
    shared = [load_scene(n).camera for n in ("contact_localisation", "calibration_chessboard",
                                             "calibration_hemispheres")]
    assert shared[0] == shared[1] == shared[2]     # one simulated unit for calibration and contacts


def test_bad_scenes_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="no scene"):
        load_scene("no_such_scene")
    with pytest.raises(ValueError, match="unknown effects"):
        load_scene("surface_mapping", effects=["sparkles"])
    with pytest.raises(ValueError, match="unknown variant"):
        load_scene("surface_mapping", variant="warp_speed")
    with pytest.raises(ValueError, match="cannot be covered"):
        load_scene("surface_mapping", **{"motion.duration": 0.5})
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_scene(bad)


def test_camera_overrides_by_any_natural_name():
    assert load_scene("surface_mapping", **{"camera.fx": 400}).camera.fx == 400
    assert load_scene("surface_mapping", **{"camera.camera.fy": 410}).camera.fy == 410
    assert load_scene("surface_mapping", **{"extrinsics.theta": 0.1}).camera.theta == 0.1
    assert load_scene("surface_mapping", **{"camera.extrinsics.d": 0.001}).camera.d == 0.001
    assert load_scene("surface_mapping", **{"cylinder.length": 0.04}).camera.length == 0.04
    with pytest.raises(ValueError, match="unknown camera parameter"):
        load_scene("surface_mapping", **{"camera.fz": 1.0})
    with pytest.raises(ValueError, match="outside the tube"):
        load_scene("surface_mapping", **{"extrinsics.d": 0.2})
