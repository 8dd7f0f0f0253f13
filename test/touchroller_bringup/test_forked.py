"""`forked`: the one place the map command's child processes (its reader, its decoding workers) start and end."""
from __future__ import annotations

import os
import time

import pytest

from touchroller_bringup.forked import end_child, fork_available, fork_child, picklable

pytestmark = pytest.mark.skipif(not fork_available(), reason="needs fork (Linux)")


def _status(pid: int) -> int:
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def test_the_child_runs_in_its_own_process_closes_what_it_is_told_and_exits_0():
    read, write = os.pipe()
    spare_r, spare_w = os.pipe()

    def run() -> None:
        try:
            os.fstat(spare_r)
            closed = b"open"
        except OSError:
            closed = b"closed"
        os.write(write, f"{os.getpid()} ".encode() + closed)

    pid = fork_child(run, close=(read, spare_r))
    os.close(write)
    said = os.read(read, 100).decode().split()
    os.close(read)
    os.close(spare_r)
    os.close(spare_w)
    assert _status(pid) == 0
    assert said == [str(pid), "closed"] and pid != os.getpid()


def test_a_failing_child_exits_1_without_a_traceback(capfd):
    def run() -> None:
        raise ValueError("boom")

    assert _status(fork_child(run)) == 1
    assert "Traceback" not in capfd.readouterr().err


def test_a_child_still_at_work_is_ended_when_the_parent_stops_early():
    pid = fork_child(lambda: time.sleep(60))
    started = time.monotonic()
    end_child(pid, wait=False)
    assert time.monotonic() - started < 10
    with pytest.raises(ChildProcessError):   # reaped
        os.waitpid(pid, os.WNOHANG)


def test_an_exception_that_does_not_pickle_becomes_its_type_and_text():
    class Local(Exception):   # a local class does not pickle
        pass

    assert isinstance(picklable(ValueError("x")), ValueError)
    converted = picklable(Local("lost"))
    assert isinstance(converted, RuntimeError) and str(converted) == "Local: lost"
