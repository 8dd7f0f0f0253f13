"""`decode_pool.ordered`: work on a stream's items by forked processes, the stream kept in order."""
from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from touchroller_bringup.decode_pool import WorkerProcessError, ordered, pool_available, pool_workers

pytestmark = pytest.mark.skipif(not pool_available(), reason="the worker processes need fork (Linux)")


def _stream(count: int):
    """Frames (arrays saying their number) among transforms (strings), as a recording interleaves them."""
    for k in range(count):
        if k % 3 == 0:
            yield f"tf {k}"
        yield np.full((5, 7), k, np.uint8)


def _work(frame: np.ndarray) -> tuple[int, int, np.ndarray]:
    return int(frame[0, 0]), os.getpid(), frame.astype(np.float32) * 2


def _frame(item) -> bool:
    return isinstance(item, np.ndarray)


@pytest.mark.parametrize(("workers", "slots"), [(2, 1), (2, 4), (3, 2), (5, 3)])
def test_the_frames_come_back_worked_on_in_order_among_the_other_items(workers, slots):
    got = list(ordered(_stream(100), _work, _frame, workers, slots=slots))
    inline = list(ordered(_stream(100), _work, _frame, 1))
    assert len(got) == len(inline) == 134
    for a, b in zip(got, inline, strict=True):
        if isinstance(b, str):
            assert a == b
        else:
            assert a[0] == b[0] and np.array_equal(a[2], b[2]) and a[2].dtype == np.float32
    pids = {item[1] for item in got if isinstance(item, tuple)}
    assert os.getpid() not in pids and len(pids) == workers   # every worker had a share
    assert {item[1] for item in inline if isinstance(item, tuple)} == {os.getpid()}


def test_an_item_too_large_for_a_slot_is_worked_on_in_its_place():
    items = [np.full(10, 1, np.uint8), np.full(100_000, 2, np.uint8), np.full(10, 3, np.uint8)]
    got = list(ordered(items, lambda a: (int(a[0]), os.getpid()), _frame, 2, slot_bytes=10_000))
    assert [g[0] for g in got] == [1, 2, 3] and got[1][1] == os.getpid() and got[0][1] != os.getpid()


def test_a_result_too_large_for_a_slot_follows_through_the_pipe():
    got = list(ordered(_stream(20), lambda a: np.full(50_000, a[0, 0], np.uint8), _frame, 2, slot_bytes=20_000))
    frames = [g for g in got if isinstance(g, np.ndarray)]
    assert [int(f[0]) for f in frames] == list(range(20)) and all(f.size == 50_000 for f in frames)


def test_an_error_in_the_work_is_raised_at_its_place_after_the_items_before_it():
    def work(frame):
        if frame[0, 0] == 7:
            raise ValueError("frame 7 does not decode")
        return int(frame[0, 0])

    seen = []
    with pytest.raises(ValueError, match="frame 7 does not decode"):
        for item in ordered(_stream(30), work, _frame, 3):
            seen.append(item)
    assert [s for s in seen if isinstance(s, int)] == list(range(7))


def test_an_error_that_does_not_pickle_is_raised_at_its_place_as_its_type_and_text():
    class Unpicklable(Exception):   # a local class: pickle cannot find it by name in the worker's reply
        pass

    def work(frame):
        if frame[0, 0] == 4:
            raise Unpicklable("frame 4 is odd")
        return int(frame[0, 0])

    seen = []
    with pytest.raises(RuntimeError, match="^Unpicklable: frame 4 is odd$"):
        for item in ordered(_stream(20), work, _frame, 2):
            seen.append(item)
    assert [s for s in seen if isinstance(s, int)] == list(range(4))

def _children() -> set[int]:
    with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as stream:
        return {int(pid) for pid in stream.read().split()}


def test_a_dying_worker_is_one_clear_error_not_a_hang():
    before = _children()

    def work(frame):
        if frame[0, 0] == 11:
            os.kill(os.getpid(), signal.SIGKILL)   # as the kernel's OOM killer would
        return int(frame[0, 0])

    start = time.monotonic()
    with pytest.raises(WorkerProcessError, match="worker process ended unexpectedly"):
        list(ordered(_stream(200), work, _frame, 2))
    assert time.monotonic() - start < 30
    assert _children() == before   # the other workers ended and were reaped


def test_a_consumer_that_stops_early_leaves_no_worker_behind():
    before = _children()
    stream = ordered(_stream(500), _work, _frame, 3)
    for _ in range(10):
        next(stream)
    assert len(_children() - before) == 3
    stream.close()
    assert _children() == before


def test_one_worker_or_none_wanted_works_in_this_process_and_starts_no_worker():
    before = _children()
    assert [x for x in ordered(["a", "b"], _work, _frame, 4)] == ["a", "b"]   # nothing to work on
    assert _children() == before
    assert pool_workers() >= 1 and pool_workers(limit=1) == 1
    with pytest.raises(ValueError):
        list(ordered([], _work, _frame, 0))
