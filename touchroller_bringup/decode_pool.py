"""Work on some items of a stream done by a pool of forked worker processes, the stream kept in order.

`touchroller map` on a compressed recording spends most of its time decoding the frames' PNGs. One
process reading the bag cannot keep up with the mapping; `ordered(items, work, wanted, workers)` gives
`items` in their order, each item `wanted(item)` says is worth it replaced by `work(item)`, computed by
`workers` forked processes (they inherit the caller's set-up, so `work` need not pickle; the items and
results do). Other items (the transforms between the frames) pass through in their place.

* Hand-over: the wanted items go to the workers in turn (item k to worker k mod n), so their results are
  read back in the same turn and the order needs no bookkeeping. An item and its result cross in
  memory shared with the worker (a slot of `slot_bytes` each way, pickled once; a pipe carries only a
  few bytes to say which slot), so the caller never waits on a pipe full of pixels and a worker never
  waits for the caller to write. An item too large for a slot is worked on by the caller itself; a
  result too large follows its message through the worker's pipe. (concurrent.futures'
  ProcessPoolExecutor moves both through pipes and threads: about 0.8 ms of CPU per VGA frame, half
  what decoding it costs.)
* Memory: each worker has `slots` items on their way at most; reading the stream waits for the oldest.
* Errors: an exception in `work` is raised at its item's place, after the items before it. A worker that
  dies (killed, out of memory) is `WorkerProcessError`, one line, never a hang: its pipe ends. Workers
  end with the process that made them (PR_SET_PDEATHSIG) and ignore Ctrl-C (the caller handles it and
  ends them); a caller that stops early ends them too.
POSIX only (`pool_available`); elsewhere, or with one worker, `work` runs in the caller's process.
"""
from __future__ import annotations

import mmap
import os
import pickle
import struct
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

from touchroller_bringup.forked import end_child, fork_available, fork_child, picklable

T = TypeVar("T")
R = TypeVar("R")
MAX_WORKERS = 8
_TASK = struct.Struct("<II")     # slot, number of parts of the pickled item in it (lengths follow, <Q each)
_DONE = struct.Struct("<BI")     # 0: the result is in the slot, 1: it follows on the pipe; its number of parts
_LENGTH = struct.Struct("<Q")


def _parts(value: Any) -> list[memoryview]:
    """`value` pickled (protocol 5): the pickle, then the bytes of its arrays as they are (out-of-band: not
    copied into the pickle)."""
    buffers: list[pickle.PickleBuffer] = []
    body = pickle.dumps(value, 5, buffer_callback=buffers.append)
    return [memoryview(body), *(buffer.raw() for buffer in buffers)]


def _header(head: bytes, parts: list[memoryview]) -> bytes:
    return head + b"".join(_LENGTH.pack(part.nbytes) for part in parts)


def _put(memory: mmap.mmap, start: int, parts: list[memoryview]) -> None:
    for part in parts:
        memory[start:start + part.nbytes] = part
        start += part.nbytes


def _get(memory: mmap.mmap | memoryview, start: int, lengths: list[int], copy: bool) -> Any:
    """The value `_put` wrote at `start`: its arrays copied out (`copy`), or views of the shared memory."""
    view = memoryview(memory)
    parts = []
    for length in lengths:
        part = view[start:start + length]
        parts.append(bytearray(part) if copy else part)
        start += length
    return pickle.loads(parts[0], buffers=parts[1:])


def _lengths(stream: Any, count: int) -> list[int] | None:
    data = _read_exactly(stream, count * _LENGTH.size)
    return None if data is None else [v for (v,) in _LENGTH.iter_unpack(data)]


class WorkerProcessError(RuntimeError):
    """A worker process ended without saying why (killed, or out of memory)."""


def pool_available() -> bool:
    """Whether `ordered` may use worker processes: Linux's fork (see `forked.fork_available`)."""
    return fork_available()


def pool_workers(limit: int = MAX_WORKERS) -> int:
    """The processors this process may run on (its CPU affinity, else `os.cpu_count()`), at most `limit`."""
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):   # not Linux
        count = os.cpu_count() or 1
    return max(1, min(count, limit))


class _Worker:
    """One forked worker: its pipes and its shared slots (an item area and a result area each)."""

    def __init__(self, slots: int, slot_bytes: int) -> None:
        self.slots, self.slot_bytes = slots, slot_bytes
        self.memory = mmap.mmap(-1, 2 * slots * slot_bytes)   # anonymous and shared: the fork sees the same pages
        self.task_r, self.task_w = os.pipe()
        self.done_r, self.done_w = os.pipe()
        self.pid = 0
        self.sent = 0       # items handed to it so far
        self.waiting = 0    # of them, those whose results were not taken back yet
        self.stream: Any = None

    def area(self, slot: int, result: bool) -> tuple[int, int]:
        start = (2 * slot + int(result)) * self.slot_bytes
        return start, start + self.slot_bytes

    def start(self, work: Callable[[Any], Any], everyone: list[_Worker]) -> None:
        # only its own ends stay open in the worker: a pipe ends when its worker does
        others = [fd for other in everyone for fd in ((other.task_w, other.done_r) if other is self else
                                                      (other.task_r, other.task_w, other.done_r, other.done_w))]
        self.pid = fork_child(lambda: self._serve(work), close=others, interrupt=False)
        os.close(self.task_r)
        os.close(self.done_w)
        self.stream = os.fdopen(self.done_r, "rb", buffering=1 << 16)

    def _serve(self, work: Callable[[Any], Any]) -> None:
        tasks = os.fdopen(self.task_r, "rb", buffering=0)
        done = os.fdopen(self.done_w, "wb", buffering=1 << 16)
        while True:
            header = _read_exactly(tasks, _TASK.size)
            if header is None:
                return   # the caller closed the pipe: no more items
            slot, count = _TASK.unpack(header)
            lengths = _lengths(tasks, count)
            if lengths is None:
                return
            try:   # the item's arrays are views of its slot, which stays the item's until its result is taken
                result: tuple[Any, BaseException | None] = (work(_get(self.memory, self.area(slot, False)[0],
                                                                      lengths, copy=False)), None)
                parts = _parts(result)
            except Exception as exc:  # noqa: BLE001 - raised again by the caller, at this item's place
                parts = _parts((None, picklable(exc)))
            start, end = self.area(slot, True)
            if sum(part.nbytes for part in parts) <= end - start:
                _put(self.memory, start, parts)
                done.write(_header(_DONE.pack(0, len(parts)), parts))
            else:
                done.write(_header(_DONE.pack(1, len(parts)), parts))
                for part in parts:
                    done.write(part)
            done.flush()

    def send(self, item: Any) -> bool:
        """Hand `item` to the worker; False when it does not fit a slot (the caller works on it)."""
        parts = _parts(item)
        if sum(part.nbytes for part in parts) > self.slot_bytes:
            return False
        slot = self.sent % self.slots
        _put(self.memory, self.area(slot, False)[0], parts)
        try:
            os.write(self.task_w, _header(_TASK.pack(slot, len(parts)), parts))
        except BrokenPipeError:
            raise _died() from None
        self.sent += 1
        self.waiting += 1
        return True

    def receive(self, slot: int) -> Any:
        """The result of the item in `slot` (the oldest on its way)."""
        self.waiting -= 1
        header = _read_exactly(self.stream, _DONE.size)
        if header is None:
            raise _died()
        kind, count = _DONE.unpack(header)
        lengths = _lengths(self.stream, count)
        if lengths is None:
            raise _died()
        if kind == 0:
            value, error = _get(self.memory, self.area(slot, True)[0], lengths, copy=True)
        else:
            body = _read_exactly(self.stream, sum(lengths))
            if body is None:
                raise _died()
            value, error = _get(memoryview(body), 0, lengths, copy=True)
        if error is not None:
            raise error
        return value

    def end(self, wait: bool) -> None:
        _close(self.task_w)
        if self.stream is not None:
            self.stream.close()
        if self.pid:
            end_child(self.pid, wait)
        self.memory.close()


def _close(fd: int) -> None:
    try:
        os.close(fd)
    except OSError:
        pass


def _read_exactly(stream: Any, size: int) -> bytes | None:
    data = stream.read(size)
    while data is not None and 0 < len(data) < size:   # an unbuffered pipe may return less
        more = stream.read(size - len(data))
        if not more:
            return None
        data += more
    return data if data is not None and len(data) == size else None


def _died() -> WorkerProcessError:
    return WorkerProcessError("a decoding worker process ended unexpectedly (killed, or out of memory)")


def ordered(items: Iterable[T], work: Callable[[T], R], wanted: Callable[[T], bool], workers: int,
            slots: int = 4, slot_bytes: int = 4 << 20) -> Iterator[T | R]:
    """`items` in order, the `wanted` ones as `work(item)` computed by `workers` processes (see the module
    docstring); `slots` items per worker on their way at most, each pickled in `slot_bytes` or less."""
    if workers < 1 or slots < 1 or slot_bytes < 1:
        raise ValueError(f"need workers, slots and slot_bytes >= 1, got {workers}, {slots}, {slot_bytes}")
    if workers == 1 or not pool_available():
        for item in items:
            yield work(item) if wanted(item) else item
        return
    pool: list[_Worker] = []   # started at the first wanted item (a stream may have none)
    queue: deque[tuple[_Worker | None, Any]] = deque()   # (None, item or result) passes; (worker, slot) awaits
    turn = 0
    finished = False
    try:
        for item in items:
            if not wanted(item):
                queue.append((None, item))
            else:
                if not pool:
                    pool = [_Worker(slots, slot_bytes) for _ in range(workers)]
                    for worker in pool:
                        worker.start(work, pool)
                worker = pool[turn % workers]
                while worker.waiting >= slots:   # its slots are all taken: wait
                    yield _take(queue)
                slot = worker.sent % slots
                if worker.send(item):
                    queue.append((worker, slot))
                    turn += 1
                else:   # too large for a slot: worked on here, in its place
                    queue.append((None, work(item)))
            while queue and queue[0][0] is None:
                yield queue.popleft()[1]
        while queue:
            yield _take(queue)
        finished = True
    finally:
        for worker in pool:
            worker.end(wait=finished)


def _take(queue: deque[tuple[_Worker | None, Any]]) -> Any:
    owner, value = queue.popleft()
    return value if owner is None else owner.receive(value)
