"""The sweep node's `Sweep` action (touchroller_interfaces/action/Sweep, `/touchroller/sweep`): a sweep with
feedback (pass, coverage, distance), cancel and a result, beside the `~/start` / `~/stop` Trigger services.

Safety (docs/ur5.md, "The Sweep action"):
- a goal is accepted only when the checks of a `~/start` answered success pass, run the same way (planned
  and checked whole on the planner thread, then the arm thread's checks: connected, no fault, no sweep
  running) but without moving the arm; the arm moves only once the goal is accepted, when it executes
  (the same commit as `~/start`, so a start refused then, e.g. a fault in between, aborts the goal and
  never moves the arm);
- one sweep at a time: a goal sent while a goal or a `~/start` sweep runs is rejected (never preempts a
  moving arm), and `~/start` answers failure while a goal runs;
- cancel stops the arm exactly as `~/stop` does (the same call), then the goal ends CANCELLED;
- the goal's client gone from the ROS graph (every action client of this action that was there when the
  goal was accepted), the goal aborted for any reason, or its execution failing, stops the arm;
- every fault aborts the goal with the fault's message.

Feedback is published from the arm thread at most `FEEDBACK_PERIOD_S` apart (and whenever the pass or the
phase changes). Where touchroller_interfaces is not installed (an older build) the action server is absent:
`make_sweep_action` logs one warning and returns None.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Any

from touchroller_driver.arm import SweepPhase, SweepPlan, SweepStatus, raster_coverage

if TYPE_CHECKING:
    from touchroller_bringup.nodes.sweep_node import SweepNode

#: wall seconds between two feedback messages of a running goal (sooner when the pass or phase changes)
FEEDBACK_PERIOD_S = 0.1
#: how often the arm thread looks on the ROS graph for the goal's client, s
CLIENT_CHECK_PERIOD_S = 0.5
#: an accepted goal whose execution has not begun within this is given up (the accept answer was lost)
ACCEPT_TIMEOUT_S = 10.0

# goal field -> the sweep parameter it overrides; a scalar field < 0 and an empty array leave the parameter
SCALAR_FIELDS = {"length": "sweep.length", "speed": "sweep.speed", "depth": "sweep.depth", "accel": "sweep.accel",
                 "approach_speed": "sweep.approach_speed", "overlap": "sweep.overlap"}
ARRAY_FIELDS = {"area": ("sweep.area", 4), "start_pose": ("sweep.start_pose", 6), "direction": ("sweep.direction", 3)}


class Outcome(IntEnum):
    """The result's `outcome` (the constants of Sweep.Result)."""

    SUCCEEDED = 0
    CANCELLED = 1
    STOPPED = 2
    FAULT = 3


@dataclass(frozen=True)
class SweepFeedback:
    pass_index: int     # the pass under way or last rolled, 1-based; 0 before the first
    pass_count: int
    coverage: float     # 0..1
    distance: float     # m rolled
    phase: str


@dataclass(frozen=True)
class SweepResult:
    outcome: Outcome
    message: str
    passes_done: int
    pass_count: int
    distance: float


def goal_settings(goal: Any, settings: dict[str, Any]) -> dict[str, Any]:
    """The sweep parameters for `goal`: `settings` (the node's) with the goal's fields over them. One-line
    ValueError for a field that cannot be a parameter value (wrong length, not finite); the plan's checks
    (limits, reach, duration) come after, as for `~/start`."""
    merged = dict(settings)
    for field_name, parameter in SCALAR_FIELDS.items():
        value = float(getattr(goal, field_name))
        if value != value or value in (float("inf"), float("-inf")):
            raise ValueError(f"goal {field_name} must be finite, got {value}")
        if value >= 0.0:
            merged[parameter] = value
    for field_name, (parameter, size) in ARRAY_FIELDS.items():
        values = [float(v) for v in getattr(goal, field_name)]
        if not values:
            continue
        if len(values) != size:
            raise ValueError(f"goal {field_name} takes {size} numbers (or none for {parameter}), got {values}")
        if field_name == "area" and not (values[2] >= 0.0 and values[3] >= 0.0):
            raise ValueError(f"goal area [x, y, length, width] needs length and width >= 0 m, got {values}")
        merged[parameter] = values
    return merged


def sweep_feedback(plan: SweepPlan | None, status: SweepStatus, area_width: float) -> SweepFeedback:
    """Pass, coverage and distance of `plan` at `status` (`area_width`: the raster's width across, m)."""
    if plan is None or not plan.rolls:
        return SweepFeedback(0, 0, 0.0, 0.0, status.phase.value)
    count = len(plan.rolls)
    if status.roll is None:
        return SweepFeedback(0, count, 0.0, 0.0, status.phase.value)
    roll, fraction = min(status.roll, count - 1), min(max(status.roll_fraction, 0.0), 1.0)
    distance = float(sum(plan.lengths[:roll]) + plan.lengths[roll] * fraction)
    coverage = raster_coverage(plan, area_width, roll, fraction) / 100.0
    return SweepFeedback(roll + 1, count, min(max(coverage, 0.0), 1.0), distance, status.phase.value)


def passes_done(feedback: SweepFeedback, status: SweepStatus) -> int:
    """Passes rolled whole at `status`."""
    if status.phase is SweepPhase.DONE:
        return feedback.pass_count
    if feedback.pass_index == 0:
        return 0
    return feedback.pass_index if status.roll_fraction >= 1.0 else feedback.pass_index - 1


@dataclass
class _Goal:
    """An accepted goal's state, shared by the executor (accept, execute, cancel) and the arm thread."""

    settings: dict[str, Any]
    clients: frozenset[bytes]              # the action clients' feedback subscriptions when it was accepted
    accepted_at: float
    handle: Any = None
    started: bool = False                  # the arm thread started its sweep
    plan: SweepPlan | None = None          # ... this plan
    cancel_requested: bool = False
    ended: threading.Event | None = None   # set by the arm thread with `result`
    result: SweepResult | None = None
    last_feedback: SweepFeedback | None = None
    last_feedback_at: float = 0.0
    last_client_check: float = 0.0


class _Yield:
    """Awaitable that gives the executor back once (an rclpy coroutine callback resumes on its next spin)."""

    def __await__(self) -> Any:
        yield


class SweepActionServer:
    """The `Sweep` action of `node` (a SweepNode); built by `make_sweep_action`."""

    def __init__(self, node: SweepNode, action_type: Any) -> None:
        from rclpy.action import ActionServer, CancelResponse, GoalResponse
        from rclpy.callback_groups import ReentrantCallbackGroup

        from touchroller_bringup import names

        self.node = node
        self.action_type = action_type
        self._goal_response, self._cancel_response = GoalResponse, CancelResponse
        self._lock = threading.Lock()
        self._goal: _Goal | None = None
        self.last_rejection: str | None = None   # why the last goal was rejected (also on the log)
        self.name = names.topic(names.SWEEP_ACTION, node.get_namespace().strip("/"))
        self._feedback_topic = f"{self.name}/_action/feedback"
        # reentrant: a cancel (which stops the arm) is taken while a goal's execute coroutine waits
        self.server = ActionServer(node, action_type, names.SWEEP_ACTION, execute_callback=self._execute,
                                   goal_callback=self._on_goal, cancel_callback=self._on_cancel,
                                   handle_accepted_callback=self._on_accepted,
                                   callback_group=ReentrantCallbackGroup())

    # -- executor: accept or reject, execute, cancel --------------------------------------------
    def _reject(self, reason: str) -> Any:
        self.last_rejection = reason
        self.node.get_logger().error(f"Sweep goal rejected: {reason}")
        return self._goal_response.REJECT

    def _on_goal(self, goal: Any) -> Any:
        with self._lock:   # reserve first: a second goal meanwhile is rejected
            current = self._goal
            if current is not None and current.handle is None and \
                    time.monotonic() - current.accepted_at > ACCEPT_TIMEOUT_S:
                current = self._goal = None   # accepted, never executed (its accept answer was lost)
            if current is not None:
                return self._reject("a Sweep goal is running (one sweep at a time; cancel it first)")
            reservation = self._goal = _Goal({}, frozenset(), time.monotonic())
        try:   # not under the lock: the arm thread's loop takes it
            settings = goal_settings(goal, self.node.settings)
            success, message = self.node.check_start(settings)
        except ValueError as exc:
            success, message = False, str(exc)
        with self._lock:
            if not success:
                self._goal = None
                return self._reject(message)
            reservation.settings, reservation.clients = settings, self._client_endpoints()
            reservation.accepted_at = time.monotonic()
        self.last_rejection = None
        return self._goal_response.ACCEPT

    def _on_accepted(self, handle: Any) -> None:
        with self._lock:
            goal = self._goal
            if goal is not None and goal.handle is None:
                goal.handle = handle
        handle.execute()

    def _on_cancel(self, handle: Any) -> Any:
        with self._lock:
            goal = self._goal
            ours = goal is not None and goal.handle is handle
            if ours:
                assert goal is not None
                goal.cancel_requested = True
        if ours and goal is not None and goal.started:
            self.node.request_stop()   # exactly ~/stop
        return self._cancel_response.ACCEPT

    async def _execute(self, handle: Any) -> Any:
        with self._lock:
            goal = self._goal if self._goal is not None and self._goal.handle is handle else None
        if goal is None:   # not the goal this server accepted (cannot happen); never moves the arm
            handle.abort()
            return self._result_message(SweepResult(Outcome.FAULT, "not the accepted goal", 0, 0, 0.0))
        try:
            return await self._run(goal, handle)
        finally:
            # the execution ended before the goal's sweep (an exception, the coroutine closed): stop the arm,
            # before the goal is let go (then a ~/start may begin a sweep that is not the goal's)
            if goal.started and goal.ended is not None and not goal.ended.is_set() and self.node.active:
                self.node.request_stop()
            with self._lock:
                if self._goal is goal:
                    self._goal = None

    async def _run(self, goal: _Goal, handle: Any) -> Any:
        if goal.cancel_requested or handle.is_cancel_requested:
            return self._finish(handle, goal, SweepResult(Outcome.CANCELLED, "cancelled before the arm moved",
                                                          0, 0, 0.0))
        goal.ended = threading.Event()
        success, message = self.node.start_goal(goal.settings, self)
        if not success:
            return self._finish(handle, goal, SweepResult(Outcome.FAULT, f"start refused: {message}", 0, 0, 0.0))
        self.node.get_logger().info(f"Sweep goal: {message}")
        if goal.cancel_requested:   # cancelled while it started (a multi-threaded executor): stop it as ~/stop
            self.node.request_stop()
        while not goal.ended.is_set():
            await _Yield()
        assert goal.result is not None
        if goal.cancel_requested:   # the stop came from the cancel: wait for rclpy's CANCELING state
            deadline = time.monotonic() + 1.0
            while not handle.is_cancel_requested and time.monotonic() < deadline:
                await _Yield()
        return self._finish(handle, goal, goal.result)

    def _finish(self, handle: Any, goal: _Goal, result: SweepResult) -> Any:
        if result.outcome is Outcome.SUCCEEDED:
            handle.succeed()
        elif handle.is_cancel_requested and result.outcome in (Outcome.CANCELLED, Outcome.STOPPED):
            result = SweepResult(Outcome.CANCELLED, result.message, result.passes_done, result.pass_count,
                                 result.distance)
            handle.canceled()
        else:
            handle.abort()
        log = self.node.get_logger()
        text = f"Sweep goal {result.outcome.name.lower()}: {result.message} ({result.passes_done}/" \
               f"{result.pass_count} passes, {result.distance:.4g} m)"
        (log.info if result.outcome is Outcome.SUCCEEDED else log.warning)(text)
        return self._result_message(result)

    def _result_message(self, result: SweepResult) -> Any:
        message = self.action_type.Result()
        message.outcome, message.message = int(result.outcome), result.message
        message.passes_done, message.pass_count, message.distance = result.passes_done, result.pass_count, \
            result.distance
        return message

    # -- the arm thread: feedback, the end of the goal's sweep, its client ------------------------
    @property
    def running(self) -> bool:
        """A goal has been accepted and has not ended (`~/start` answers failure meanwhile)."""
        with self._lock:
            return self._goal is not None

    def owns_start(self, plan: SweepPlan) -> None:
        """The arm thread started the current goal's sweep, `plan` (just after its first motion command)."""
        with self._lock:
            if self._goal is not None:
                self._goal.started, self._goal.plan = True, plan

    def on_step(self, status: SweepStatus, sequencer_plan: SweepPlan | None, active: bool,
                stop: Callable[[str], None]) -> None:
        """Called by the arm thread after every loop with the sequencer's status and plan and whether a sweep
        is under way: feedback, the client check and the goal's end. `stop(message)` stops the arm (from
        the arm thread)."""
        with self._lock:
            goal = self._goal
        if goal is None or not goal.started or goal.plan is None or goal.ended is None or goal.ended.is_set():
            return
        began = sequencer_plan is goal.plan   # simulated, a sweep waits for the clock's whole second
        area = goal.settings.get("sweep.area", [0.0, 0.0, 0.0, 0.0])
        if began:
            feedback = sweep_feedback(goal.plan, status, float(area[3]) if goal.plan.passes else 0.0)
        else:
            feedback = SweepFeedback(0, len(goal.plan.rolls), 0.0, 0.0,
                                     SweepPhase.MOVING.value if active else SweepPhase.STOPPED.value)
        now = time.monotonic()
        if active and now - goal.last_client_check >= CLIENT_CHECK_PERIOD_S:
            goal.last_client_check = now
            present = self._client_endpoints()
            if not goal.clients:   # not discovered yet when the goal was accepted: the first ones seen
                goal.clients = present
            elif not (goal.clients & present):
                self.node.get_logger().error("Sweep goal: its client left the ROS graph; stopping the arm")
                stop("the Sweep goal's client left the ROS graph")
                return   # the next loop sees the sweep stopped
        last = goal.last_feedback
        if last is None or now - goal.last_feedback_at >= FEEDBACK_PERIOD_S or \
                (last.pass_index, last.phase) != (feedback.pass_index, feedback.phase):
            goal.last_feedback, goal.last_feedback_at = feedback, now
            self._publish_feedback(goal, feedback)
        if active:
            return
        if began:
            outcome = {SweepPhase.DONE: Outcome.SUCCEEDED, SweepPhase.FAULT: Outcome.FAULT}.get(
                status.phase, Outcome.CANCELLED if goal.cancel_requested else Outcome.STOPPED)
            message, done = status.message or status.phase.value, passes_done(feedback, status)
        elif status.phase is SweepPhase.FAULT:   # e.g. the deferred start's first move refused
            outcome, message, done = Outcome.FAULT, status.message or "arm fault", 0
        else:
            outcome = Outcome.CANCELLED if goal.cancel_requested else Outcome.STOPPED
            message, done = "stopped before the roll began", 0
        goal.result = SweepResult(outcome, message, done, feedback.pass_count, feedback.distance)
        goal.ended.set()
        self._wake()

    def end(self, message: str) -> None:
        """End the running goal as STOPPED with `message` (the node is going away, or this server failed
        on the arm thread; the arm is stopped by the caller)."""
        with self._lock:
            goal = self._goal
        if goal is not None and goal.ended is not None and not goal.ended.is_set():
            last = goal.last_feedback or SweepFeedback(0, 0, 0.0, 0.0, SweepPhase.STOPPED.value)
            goal.result = SweepResult(Outcome.STOPPED, message, max(last.pass_index - 1, 0), last.pass_count,
                                      last.distance)
            goal.ended.set()
            self._wake()

    def _publish_feedback(self, goal: _Goal, feedback: SweepFeedback) -> None:
        message = self.action_type.Feedback()
        message.pass_index, message.pass_count = feedback.pass_index, feedback.pass_count
        message.coverage, message.distance, message.phase = feedback.coverage, feedback.distance, feedback.phase
        try:
            goal.handle.publish_feedback(message)
        except Exception:  # noqa: BLE001 - the context went down between the check and the publish
            if self.node.context.ok():
                raise

    def _client_endpoints(self) -> frozenset[bytes]:
        """The feedback subscriptions on this action (every action client has one), by endpoint id."""
        try:
            infos = self.node.get_subscriptions_info_by_topic(self._feedback_topic)
        except Exception:  # noqa: BLE001 - the node or context is going down
            return frozenset()
        return frozenset(bytes(info.endpoint_gid) for info in infos)

    def _wake(self) -> None:
        executor = self.node.executor
        if executor is not None:
            executor.wake()

    def destroy(self) -> None:
        self.end("the sweep node is shutting down")
        self.server.destroy()


def make_sweep_action(node: SweepNode) -> SweepActionServer | None:
    """The node's Sweep action server, or None (one warning) where touchroller_interfaces is not built."""
    try:
        from touchroller_interfaces.action import Sweep
    except ImportError:
        node.get_logger().warning("the Sweep action is not offered: touchroller_interfaces is not installed "
                                  "(build it: docs/ur5.md); ~/start and ~/stop work as before")
        return None
    return SweepActionServer(node, Sweep)
