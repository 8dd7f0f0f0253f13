"""Every node's console-script entry starts its node and shuts down cleanly on Ctrl-C."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from touchroller_bringup.ros_domains import reserve_domain_id

pytest.importorskip("rclpy")

NODE_MODULES = (
    "touchroller_driver.camera_node",
    "touchroller_driver.sweep_node",
    "touchroller_perception.perception_node",
    "touchroller_perception.calibration_node",
)


@pytest.mark.parametrize("module", NODE_MODULES)
def test_main_spins_the_node_and_exits_cleanly_on_sigint(module, tmp_path):
    with reserve_domain_id() as lease:   # no other process on this host uses it
        env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        process = subprocess.Popen([sys.executable, "-c", f"from {module} import main; main()"], cwd=tmp_path,
                                   env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(3.0)                                   # long enough to construct the node and spin
        assert process.poll() is None, f"{module} exited early:\n{process.stdout.read()}"
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=20)
    assert process.returncode == 0, output
    assert "Traceback" not in output, output
