"""Every node's trigger services are std_srvs/Trigger, and still work where std_srvs is missing."""
from __future__ import annotations

import sys

import pytest

pytest.importorskip("rclpy")
pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from touchroller_bringup.ros_services import trigger_service_type  # noqa: E402

EXPECTED = {
    "/touchroller_perception/recapture_reference",
    "/touchroller_sweep/start", "/touchroller_sweep/stop",
    "/touchroller_calibration/capture", "/touchroller_calibration/solve", "/touchroller_calibration/reset",
}


def make_nodes(context) -> list[Node]:
    from touchroller_bringup.nodes.calibration_node import CalibrationNode
    from touchroller_bringup.nodes.perception_node import PerceptionNode
    from touchroller_bringup.nodes.sweep_node import SweepNode

    return [PerceptionNode("touchroller_perception", context=context,
                           parameter_overrides=[Parameter("map.publish_rate", value=0.0)]),
            SweepNode(context=context),
            CalibrationNode(context=context, parameter_overrides=[Parameter("output_path", value="")])]


def services_of(nodes: list[Node], probe: Node, spin_until, executor) -> dict[str, list[str]]:
    def found() -> dict[str, list[str]]:
        return {name: types for name, types in probe.get_service_names_and_types() if name in EXPECTED}

    spin_until(executor, lambda: set(found()) == EXPECTED, timeout=20)
    return found()


def call(probe: Node, executor, spin_until, name: str, service_type: type):
    client = probe.create_client(service_type, name)
    assert spin_until(executor, client.service_is_ready, timeout=20)
    future = client.call_async(service_type.Request())
    assert spin_until(executor, future.done, timeout=20)
    return future.result()


@pytest.fixture
def graph(ros_context):
    nodes = make_nodes(ros_context)
    probe = Node("service_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    yield nodes, probe, executor
    executor.shutdown()
    for node in (*nodes, probe):
        node.destroy_node()


def test_services_are_std_srvs_trigger(graph, spin_until):
    pytest.importorskip("std_srvs.srv")
    nodes, probe, executor = graph
    assert trigger_service_type()[1]
    services = services_of(nodes, probe, spin_until, executor)
    assert services == {name: ["std_srvs/srv/Trigger"] for name in EXPECTED}
    answer = call(probe, executor, spin_until, "/touchroller_sweep/stop", trigger_service_type()[0])
    assert answer.success and answer.message == "arm stopped"


@pytest.fixture
def without_std_srvs(monkeypatch):
    """`import std_srvs.srv` raises ImportError, as on an install without std_srvs."""
    monkeypatch.setitem(sys.modules, "std_srvs", None)
    monkeypatch.setitem(sys.modules, "std_srvs.srv", None)


def test_without_std_srvs_the_services_fall_back_to_add_diagnostics(without_std_srvs, ros_context, spin_until):
    from diagnostic_msgs.srv import AddDiagnostics

    with pytest.raises(ImportError):
        import std_srvs.srv  # noqa: F401
    assert trigger_service_type() == (AddDiagnostics, False)
    nodes = make_nodes(ros_context)
    probe = Node("service_probe", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (*nodes, probe):
        executor.add_node(node)
    try:
        services = services_of(nodes, probe, spin_until, executor)
        assert services == {name: ["diagnostic_msgs/srv/AddDiagnostics"] for name in EXPECTED}
        # the same success/message answers as Trigger: nothing captured, so solve is refused with a reason
        solve = call(probe, executor, spin_until, "/touchroller_calibration/solve", AddDiagnostics)
        assert not solve.success and solve.message
        reset = call(probe, executor, spin_until, "/touchroller_calibration/reset", AddDiagnostics)
        assert reset.success
        recapture = call(probe, executor, spin_until, "/touchroller_perception/recapture_reference",
                         AddDiagnostics)
        assert recapture.success and "frames" in recapture.message
    finally:
        executor.shutdown()
        for node in (*nodes, probe):
            node.destroy_node()
