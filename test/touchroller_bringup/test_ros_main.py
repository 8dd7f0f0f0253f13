"""Every node's console-script entry starts its node and shuts down cleanly on Ctrl-C."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

NODE_MODULES = {
    "touchroller_bringup.nodes.camera_node": "/touchroller/camera",
    "touchroller_bringup.nodes.sweep_node": "/touchroller/sweep",
    "touchroller_bringup.nodes.perception_node": "/touchroller/perception",
    "touchroller_bringup.nodes.calibration_node": "/touchroller/calibration",
}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("module", NODE_MODULES)
def test_main_spins_the_node_and_exits_cleanly_on_sigint(module, ros_context, spin_until, tmp_path):
    """Ctrl-C once the node answers a service (so it is constructed and spinning), however long its
    start-up takes: a fixed 3 s wait sent SIGINT mid-import on a loaded machine (a traceback)."""
    from rcl_interfaces.srv import ListParameters
    from rclpy.node import Node

    # ros_context put its (exclusive) ROS_DOMAIN_ID and localhost discovery into os.environ
    process = subprocess.Popen([sys.executable, "-c", f"from {module} import main; main()"], cwd=tmp_path,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    probe = Node("main_probe", context=ros_context)
    try:
        client = probe.create_client(ListParameters, f"{NODE_MODULES[module]}/list_parameters")
        ready = spin_until(probe, lambda: client.service_is_ready() or process.poll() is not None, timeout=60.0)
        assert ready and process.poll() is None, f"{module} exited early or never came up:\n{_output(process)}"
        future = client.call_async(ListParameters.Request())
        assert spin_until(probe, future.done, timeout=20.0), f"{module} does not spin:\n{_output(process)}"
        assert future.result().result.names                    # its declared parameters: it is our node
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
    finally:
        probe.destroy_node()
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, output
    assert "Traceback" not in output, output


def _output(process: subprocess.Popen) -> str:
    if process.poll() is None:
        process.kill()
    return process.communicate()[0]


def test_ctrl_c_while_spin_builds_its_wait_set_is_a_clean_exit(ros_context, monkeypatch):
    """SIGINT's handler shuts the context down; landing between spin's context check and building its
    wait set, rclpy raises RCLError "the given context is not valid" (3 of 20 starts on a loaded
    machine exited 1 with a traceback). With the context down, run_node treats it as Ctrl-C."""
    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.node import Node

    from touchroller_bringup import ros_main

    made = []

    def spin_hit_by_ctrl_c(node):
        rclpy.shutdown()      # what rclpy's SIGINT handler does
        raise rclpy_implementation.RCLError("failed to initialize wait set: the given context is not valid")

    monkeypatch.setattr(ros_main.rclpy, "spin", spin_hit_by_ctrl_c)
    ros_main.run_node(lambda: made.append(Node("run_node_ctrl_c_probe")) or made[-1])
    assert made and not made[0].context.ok()


def test_an_rcl_error_while_the_context_is_up_is_not_swallowed(ros_context, monkeypatch):
    import rclpy
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.node import Node

    from touchroller_bringup import ros_main

    def failing_spin(node):
        raise rclpy_implementation.RCLError("a real failure")

    monkeypatch.setattr(ros_main.rclpy, "spin", failing_spin)
    with pytest.raises(rclpy_implementation.RCLError, match="a real failure"):
        ros_main.run_node(lambda: Node("run_node_error_probe"))
    assert not rclpy.ok()     # shut down all the same


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("script", "arguments", "expected"), [
    ("camera_node", ["-p", "extrinsics.theta:=10.0"], "extrinsics.theta out of range"),
    ("perception_node", ["-p", "extrinsics.theta:=abc"], "extrinsics.theta"),
    ("perception_node", ["-p", "extrinsics.d:=0.08"], "outside the tube"),
    ("sweep_node", ["-p", "sweep.speed:=-5.0"], "sweep.speed out of range"),
    ("calibration_node", ["--params-file", "not_yaml.yaml"], "Couldn't parse params file"),
])
def test_bad_start_up_parameters_are_one_line_and_exit_2(ros_context, tmp_path, script, arguments, expected):
    """As a user starts a node: its console script with a bad value gave a 27-line traceback."""
    (tmp_path / "not_yaml.yaml").write_text("a: [\n")
    executable = os.path.join(os.path.dirname(sys.executable), script)
    done = subprocess.run([executable, "--ros-args", *arguments], cwd=tmp_path, capture_output=True, text=True,
                          timeout=100, env=dict(os.environ))
    assert done.returncode == 2, done.stderr
    ours = [line for line in done.stderr.splitlines() if not line.startswith("[ERROR] [")]   # rcl logs its own
    assert len(ours) == 1 and ours[0].startswith(f"{script}: error: ") and expected in ours[0], done.stderr
    assert "Traceback" not in done.stderr and not done.stdout
