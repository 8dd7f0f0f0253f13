"""TouchRoller simulator: what the webcam inside the roller sees (no rclpy here).

    scene = load_scene("surface_mapping", variant="fast")     # config/scenes/<name>.yaml or a path
    sensor = SimulatedSensor(scene, seed=0)                    # sensor.camera is the true CameraModel
    image = sensor.render(RollerState(travel=0.01, depth=5e-4, speed=0.01))   # HxWx3 bgr8
    for frame in sensor.frames(): ...                          # Frame(stamp_ns, image, truth)

See docs/simulator.md for what is modelled and what is not.
"""
from touchroller_driver.sim.render import Frame, Indenter, RollerState, SimulatedSensor, TruthMap
from touchroller_driver.sim.scene import EFFECTS, Scene, available_scenes, load_scene

__all__ = [
    "EFFECTS", "Frame", "Indenter", "RollerState", "Scene", "SimulatedSensor", "TruthMap",
    "available_scenes", "load_scene",
]
