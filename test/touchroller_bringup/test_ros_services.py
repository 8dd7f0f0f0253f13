"""Every node's trigger services are std_srvs/Trigger, under the node's namespace."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy")
pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from touchroller_bringup import names  # noqa: E402

SERVICES = {
    (names.PERCEPTION_NODE, names.RECAPTURE_REFERENCE),
    (names.SWEEP_NODE, names.START), (names.SWEEP_NODE, names.STOP),
    (names.CALIBRATION_NODE, names.CAPTURE), (names.CALIBRATION_NODE, names.SOLVE),
    (names.CALIBRATION_NODE, names.RESET),
}


def make_nodes(context) -> list[Node]:
    from touchroller_bringup.nodes.calibration_node import CalibrationNode
    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.nodes.sweep_node import SweepNode

    return [PerceptionNode(context=context, parameter_overrides=[Parameter("map.publish_rate", value=0.0)]),
            SweepNode(context=context),
            CalibrationNode(context=context, parameter_overrides=[Parameter("output_path", value="")])]


def call(probe: Node, executor, spin_until, name: str):
    client = probe.create_client(Trigger, name)
    assert spin_until(executor, client.service_is_ready, timeout=20)
    future = client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, timeout=20)
    return future.result()


def test_services_are_std_srvs_trigger_in_the_default_namespace(ros_context, spin_until):
    nodes = make_nodes(ros_context)
    probe = Node("service_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    expected = {names.service(node, name) for node, name in SERVICES}
    assert expected >= {"/touchroller/sweep/start", "/touchroller/perception/recapture_reference"}

    def found() -> dict[str, list[str]]:
        return {name: types for name, types in probe.get_service_names_and_types() if name in expected}

    try:
        assert spin_until(executor, lambda: set(found()) == expected, timeout=20)
        assert found() == {name: ["std_srvs/srv/Trigger"] for name in expected}
        answer = call(probe, executor, spin_until, names.service(names.SWEEP_NODE, names.STOP))
        assert answer.success and answer.message == "arm stopped"
        solve = call(probe, executor, spin_until, names.service(names.CALIBRATION_NODE, names.SOLVE))
        assert not solve.success and solve.message   # nothing captured: refused, with the reason
        recapture = call(probe, executor, spin_until, names.service(names.PERCEPTION_NODE, names.RECAPTURE_REFERENCE))
        assert recapture.success and "frames" in recapture.message
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()
