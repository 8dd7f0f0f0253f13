"""The ur_rtde arm against the installed ur_rtde module (no robot: loopback only).

- every call ur5.py makes exists in the installed pybind module with an overload that takes the
  number of positional arguments we pass;
- connecting to a loopback address where nothing listens fails fast with one clear line and a fault;
- the fault/limit logic runs on autospecced doubles of the real classes (a misspelt call fails).
"""
from __future__ import annotations

import math
import re
from unittest import mock

import numpy as np
import pytest

from touchroller_driver import ur5
from touchroller_driver.arm import Arm, ArmError, ArmLimitError, ArmLimits

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")

# A loopback address nothing listens on (all of 127/8 is loopback on Linux): connection refused.
REFUSED_HOST = "127.0.0.213"
POSE = [0.4, 0.0, 0.2, math.pi, 0.0, 0.0]


def _split_top_level(text: str) -> list[str]:
    parts, depth, current = [], 0, []
    for char in text:
        if char in "[(":
            depth += 1
        elif char in "])":
            depth -= 1
        if char == "," and depth == 0:
            parts.append("".join(current).strip())
            current = []
        else:
            current.append(char)
    if "".join(current).strip():
        parts.append("".join(current).strip())
    return parts


def overload_arities(function, name: str) -> list[tuple[int, int]]:
    """(required, total) positional parameters (without self) of each pybind overload of `function`."""
    arities = []
    for match in re.finditer(rf"^(?:\d+\. )?{name}\((.*)\) -> ", function.__doc__ or "", flags=re.MULTILINE):
        params = [p for p in _split_top_level(match.group(1)) if not p.startswith("self")]
        required = sum("=" not in p for p in params)
        arities.append((required, len(params)))
    return arities


@pytest.mark.parametrize(("cls", "calls"), [
    (rtde_control.RTDEControlInterface, ur5.CONTROL_CALLS),
    (rtde_receive.RTDEReceiveInterface, ur5.RECEIVE_CALLS),
])
def test_every_call_exists_with_the_arity_we_use(cls, calls):
    for name, n_args in calls.items():
        assert hasattr(cls, name), f"{cls.__name__}.{name} does not exist in ur_rtde"
        arities = overload_arities(getattr(cls, name), name)
        assert arities, f"could not read the signature of {cls.__name__}.{name}"
        assert any(lo <= n_args <= hi for lo, hi in arities), (name, n_args, arities)


def test_constructors_take_host_and_frequency():
    for cls_name, n_args in ur5.CONSTRUCTOR_CALLS.items():
        cls = getattr(rtde_control if "Control" in cls_name else rtde_receive, cls_name)
        arities = overload_arities(cls.__init__, "__init__")
        assert any(lo <= n_args <= hi for lo, hi in arities), (cls_name, arities)


def test_signature_parser_rejects_a_wrong_arity():
    # moveL(pose, speed, accel, async) exists; moveL with 6 positional arguments does not.
    arities = overload_arities(rtde_control.RTDEControlInterface.moveL, "moveL")
    assert not any(lo <= 6 <= hi for lo, hi in arities)


def test_refused_connection_is_one_clear_line_and_a_fault():
    arm = ur5.UR5Arm(REFUSED_HOST)
    assert isinstance(arm, Arm)
    with pytest.raises(ArmError) as info:
        arm.connect()
    message = str(info.value)
    assert REFUSED_HOST in message and "\n" not in message and "cannot connect" in message
    assert arm.fault() == message
    with pytest.raises(ArmError):
        arm.tcp_pose()
    with pytest.raises(ArmError):
        arm.move_linear(POSE, 0.01, 0.1)
    arm.stop()  # harmless when not connected
    arm.disconnect()


def test_bad_robot_ip_is_rejected_up_front():
    with pytest.raises(ValueError):
        ur5.UR5Arm("")
    with pytest.raises(ValueError):
        ur5.UR5Arm("192.168.1.2 ; rm")


@pytest.fixture()
def connected_arm(monkeypatch):
    """A UR5Arm whose ur_rtde interfaces are autospecced doubles of the installed classes."""
    control = mock.create_autospec(rtde_control.RTDEControlInterface, instance=True)
    receive = mock.create_autospec(rtde_receive.RTDEReceiveInterface, instance=True)
    control.isConnected.return_value = True
    control.isPoseWithinSafetyLimits.return_value = True
    control.moveL.return_value = True
    control.getAsyncOperationProgress.return_value = 0
    control.isSteady.return_value = False
    receive.isConnected.return_value = True
    receive.isProtectiveStopped.return_value = False
    receive.isEmergencyStopped.return_value = False
    receive.getSafetyMode.return_value = 1
    receive.getActualTCPPose.return_value = list(POSE)
    monkeypatch.setattr(rtde_control, "RTDEControlInterface", lambda host, freq: control)
    monkeypatch.setattr(rtde_receive, "RTDEReceiveInterface", lambda host, freq: receive)
    arm = ur5.UR5Arm("127.0.0.1", limits=ArmLimits(max_speed=0.05, max_accel=0.5))
    arm.connect()
    return arm, control, receive


def test_limits_are_checked_before_moveL_is_sent(connected_arm):
    arm, control, _ = connected_arm
    with pytest.raises(ArmLimitError):
        arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.5, 0.1)
    control.moveL.assert_not_called()
    arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.02, 0.1)
    args = control.moveL.call_args.args
    assert args[1:] == (0.02, 0.1, True) and args[0][0] == pytest.approx(0.5)


def test_unreachable_target_is_refused(connected_arm):
    arm, control, _ = connected_arm
    control.isPoseWithinSafetyLimits.return_value = False
    with pytest.raises(ArmError, match="safety limits"):
        arm.move_linear(POSE, 0.02, 0.1)
    control.moveL.assert_not_called()


def test_protective_stop_becomes_a_fault_that_refuses_motion(connected_arm):
    arm, control, receive = connected_arm
    assert arm.fault() is None
    receive.isProtectiveStopped.return_value = True
    assert "protective stop" in arm.fault()
    with pytest.raises(ArmError, match="protective stop"):
        arm.move_linear(POSE, 0.02, 0.1)
    control.moveL.assert_not_called()


def test_lost_connection_is_a_fault(connected_arm):
    arm, control, _ = connected_arm
    control.isConnected.return_value = False
    assert "lost the RTDE connection" in arm.fault()


def test_progress_follows_the_measured_tcp(connected_arm):
    arm, control, receive = connected_arm
    arm.move_linear(np.add(POSE, [0.1, 0, 0, 0, 0, 0]), 0.02, 0.1)
    receive.getActualTCPPose.return_value = list(np.add(POSE, [0.025, 0, 0, 0, 0, 0]))
    assert arm.progress() == pytest.approx(0.25)
    assert arm.is_moving()
    arm.stop()
    control.stopL.assert_called_once_with(ur5.STOP_DECELERATION)
    assert arm.progress() == pytest.approx(0.25)
    arm.disconnect()
    control.stopScript.assert_called_once_with()
    receive.disconnect.assert_called_once_with()
