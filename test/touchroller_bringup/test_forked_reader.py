"""`read_forked`: a reader in a forked child, its arrays handed over in shared memory."""
from __future__ import annotations

import os

import numpy as np
import pytest

from touchroller_bringup.errors import UserError
from touchroller_bringup.forked_reader import ReaderProcessError, fork_available, read_forked

pytestmark = pytest.mark.skipif(not fork_available(), reason="the reader process needs fork (Linux)")
SHAPE = (7, 5)


def _items(count: int, every: int = 3):
    """Payloads 0..count-1; every `every`-th one has no array, the others an array that says its number."""
    for k in range(count):
        yield (k, os.getpid()), None if k % every == 0 else np.full(SHAPE, k, np.float32)


@pytest.mark.parametrize(("slots", "batch"), [(4, 3), (1, 1), (2, 1), (3, 3), (5, 2), (64, 8)])
def test_items_arrive_in_order_with_their_arrays_through_a_ring_smaller_than_the_stream(slots, batch):
    # the child waits on a full ring and is woken once half of it is free: no ring and batch size may hang
    got = list(read_forked(lambda: _items(200), SHAPE, slots=slots, batch=batch))
    assert [payload[0] for payload, _ in got] == list(range(200))
    assert all(payload[1] != os.getpid() for payload, _ in got)   # produced by another process
    # checked after the whole stream: each array is the parent's own copy, not a view of a slot reused since
    for (k, _), array in got:
        if k % 3 == 0:
            assert array is None
        else:
            assert array.shape == SHAPE and array.dtype == np.float32 and (array == k).all()


def test_an_error_in_the_reader_is_raised_after_the_items_before_it():
    def failing():
        yield from _items(10)
        raise UserError("bag is truncated")

    seen = []
    with pytest.raises(UserError, match="bag is truncated"):
        for payload, _ in read_forked(failing, SHAPE, slots=4, batch=3):
            seen.append(payload[0])
    assert seen == list(range(10))

    class Unpicklable(Exception):
        def __reduce__(self):
            raise TypeError("not picklable")

    def odd():
        yield from _items(2)
        raise Unpicklable("odd failure")

    with pytest.raises(RuntimeError, match="Unpicklable: odd failure"):
        list(read_forked(odd, SHAPE))


def test_a_payload_that_does_not_pickle_is_an_error_that_says_so():
    def odd():
        yield from _items(2)
        yield (lambda: None), None   # a lambda does not pickle

    with pytest.raises(Exception, match="pickle"):
        list(read_forked(odd, SHAPE, batch=1))
    with pytest.raises(Exception, match="pickle"):   # and in a batch with good items before it
        list(read_forked(odd, SHAPE, batch=8))


def test_an_array_of_another_shape_is_refused():
    def wrong():
        yield 0, np.zeros((3, 3), np.float32)

    with pytest.raises(ValueError, match="does not fit"):
        list(read_forked(wrong, SHAPE))


def test_a_reader_that_dies_is_an_error_not_a_hang():
    def dying():
        yield from _items(5)
        os._exit(3)

    with pytest.raises(ReaderProcessError):
        list(read_forked(dying, SHAPE, slots=4, batch=2))


def test_a_consumer_that_stops_early_ends_the_reader():
    def endless():
        k = 0
        while True:
            yield (k, os.getpid()), np.full(SHAPE, k, np.float32)
            k += 1

    reader = read_forked(endless, SHAPE, slots=4, batch=2)
    (first, child), _ = next(reader)
    assert first == 0 and child != os.getpid()
    os.kill(child, 0)   # the reader is running (blocked on the full ring)
    reader.close()
    with pytest.raises(ProcessLookupError):   # ended and reaped: no process, not even a zombie
        os.kill(child, 0)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGKILL"])
def test_the_reader_dies_with_its_parent(tmp_path, sig):
    """#28: `touchroller map`'s forked reader outlived its parent on SIGTERM and SIGKILL (an orphan per
    killed map) for as long as it did not touch the pipes to the parent."""
    import signal
    import subprocess
    import sys
    import time

    pid_file = tmp_path / "child.pid"
    code = f"""
import os, time
import numpy as np
from touchroller_bringup.forked_reader import read_forked

def produce():
    with open({str(pid_file)!r}, "w") as stream:
        stream.write(str(os.getpid()))
    time.sleep(60)   # a long read that touches neither pipe (a bag's index, frames it skips)
    yield None, np.zeros((2, 2), np.float32)

for _ in read_forked(produce, (2, 2)):
    pass
"""
    parent = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.monotonic() + 30
    while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.02)
    child = int(pid_file.read_text())
    parent.send_signal(getattr(signal, sig))
    parent.wait(timeout=30)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        if _zombie(child):
            break
        time.sleep(0.02)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError(f"the reader {child} outlived its parent ({sig})")


def _zombie(pid):
    try:
        with open(f"/proc/{pid}/stat") as stream:
            return stream.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_the_parent_does_its_meanwhile_work_after_forking_and_before_the_first_items():
    """`meanwhile` runs in the parent once (the child already forked: what it imports is not the child's),
    and the items come as without it."""
    import sys

    calls = []

    def produce():
        yield (os.getpid(), "_meanwhile_probe" in sys.modules), None
        yield from _items(20)

    def meanwhile():
        calls.append(os.getpid())
        sys.modules["_meanwhile_probe"] = sys   # something the parent makes that a child forked before lacks

    try:
        got = list(read_forked(produce, SHAPE, slots=4, batch=3, meanwhile=meanwhile))
    finally:
        sys.modules.pop("_meanwhile_probe", None)
    (child, child_saw), _ = got[0]
    assert calls == [os.getpid()] and child != os.getpid() and not child_saw
    assert [p[0] for p, _ in got[1:]] == list(range(20))
    assert all(a is None if k % 3 == 0 else (a == k).all() for k, (_, a) in enumerate(got[1:]))
