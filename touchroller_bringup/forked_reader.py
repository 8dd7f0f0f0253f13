"""A reader in a forked child process: items produced by a second process, arrays handed over in shared memory.

`touchroller map` reads a bag and cuts each frame's band in one stage and maps in another. As two threads
of one process they share the GIL: each SQLite or OpenCV call that releases it lets the other thread in,
and taking it back waits for that thread's next release, so the mapping thread loses a good part of its
time waiting and the two stages hardly overlap. A forked child has an interpreter of its own: the stages
really run side by side, on the second core.

`read_forked(produce, shape)` forks after the caller's imports and set-up (the child inherits them), runs
`produce()` in the child and yields its items, in order, in the parent. An item is (payload, array):
the payload is pickled and sent through a pipe in batches; the array (None, or of the given shape and
dtype: a band) is written into one slot of a ring of shared memory and copied out by the parent, so the
pixels are never copied through the kernel. The parent counts the slots it has freed in the shared
memory and wakes the child through a second pipe once half the ring is free. An exception in `produce` is
raised in the parent after the items before it; a consumer that stops early ends the child.
POSIX only (`fork_available`); the caller keeps a thread for other systems. The child is started, tied to
the parent and ended by `touchroller_bringup.forked`.
"""
from __future__ import annotations

import mmap
import os
import pickle
import struct
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from touchroller_bringup.forked import end_child, fork_available, fork_child, picklable

__all__ = ["ReaderProcessError", "fork_available", "read_forked"]

Item = tuple[Any, "np.ndarray | None"]
_HEADER = struct.Struct("<Q")   # the byte length of the pickled batch that follows


class ReaderProcessError(RuntimeError):
    """The reader process ended without saying why (killed, or out of memory)."""


class _Ring:
    """`slots` arrays of one shape and dtype in memory shared with a forked child, plus the count of
    slots the parent has taken (written by the parent only, read by the child)."""

    def __init__(self, shape: tuple[int, ...], dtype: Any, slots: int) -> None:
        self.dtype = np.dtype(dtype)
        self.shape = tuple(int(v) for v in shape)
        size = int(np.prod(self.shape)) * self.dtype.itemsize
        self._memory = mmap.mmap(-1, 8 + slots * size)   # anonymous and shared: a fork sees the same pages
        self.taken = np.frombuffer(self._memory, np.int64, 1)
        self.slots = np.frombuffer(self._memory, self.dtype, slots * int(np.prod(self.shape)), 8).reshape(
            (slots, *self.shape))

    def fits(self, array: Any) -> bool:
        return isinstance(array, np.ndarray) and array.shape == self.shape and array.dtype == self.dtype


def read_forked(produce: Callable[[], Iterator[Item]], shape: tuple[int, ...], dtype: Any = np.float32,
                slots: int = 64, batch: int = 8, meanwhile: Callable[[], None] | None = None) -> Iterator[Item]:
    """The items of `produce()`, run in a forked child (see the module docstring). Arrays must be of
    `shape` and `dtype`; `slots` of them may be on their way at once; items cross `batch` at a time.
    `meanwhile()` is run by the parent once the child is forked, before it waits for the first items
    (work the parent needs later, done while the child starts: opening the bag takes it a while)."""
    if slots < 1 or batch < 1 or batch > slots:
        raise ValueError(f"need 1 <= batch <= slots, got batch {batch}, slots {slots}")
    ring = _Ring(shape, dtype, slots)
    data_r, data_w = os.pipe()
    wake_r, wake_w = os.pipe()
    pid = fork_child(lambda: _produce(produce, ring, data_w, wake_r, batch), close=(data_r, wake_w))
    os.close(data_w)
    os.close(wake_r)
    os.set_blocking(wake_w, False)
    done = False
    try:
        if meanwhile is not None:
            meanwhile()
        with os.fdopen(data_r, "rb", buffering=1 << 16) as stream:
            yield from _consume(ring, stream, wake_w)
        done = True
    finally:
        os.close(wake_w)
        end_child(pid, wait=done)


def _produce(produce: Callable[[], Iterator[Item]], ring: _Ring, data_w: int, wake_r: int, batch: int) -> None:
    """The child's loop: items into batches, arrays into free slots; the last batch says how it ended."""
    stream = os.fdopen(data_w, "wb", buffering=1 << 16)
    slots = len(ring.slots)
    chunk: list[tuple[Any, int | None]] = []
    sent = 0   # arrays written to slots so far

    def send(end: bool, error: BaseException | None = None) -> None:
        body = pickle.dumps((chunk, end, error), pickle.HIGHEST_PROTOCOL)
        stream.write(_HEADER.pack(len(body)))
        stream.write(body)
        stream.flush()
        chunk.clear()

    try:
        for payload, array in produce():
            slot = None
            if array is not None:
                if not ring.fits(array):
                    raise ValueError(f"an array of shape {getattr(array, 'shape', None)} does not fit the "
                                     f"reader's slots {ring.shape}")
                while sent - int(ring.taken[0]) >= slots:   # the ring is full: wait for the parent
                    if chunk:
                        send(False)
                    if not os.read(wake_r, 1 << 16):
                        return   # the parent has gone
                slot = sent % slots
                ring.slots[slot] = array
                sent += 1
            chunk.append((payload, slot))
            if len(chunk) >= batch:
                send(False)
        send(True)
    except Exception as exc:  # noqa: BLE001 - raised again in the parent, after the items before it
        try:
            send(True, picklable(exc))
        except Exception:  # noqa: BLE001 - the items themselves do not pickle: the error alone
            chunk.clear()
            send(True, picklable(exc))


def _consume(ring: _Ring, stream: Any, wake_w: int) -> Iterator[Item]:
    taken = woken = 0
    # The child usually runs ahead and waits on a full ring. Waking it costs the parent a context switch
    # (often half a millisecond on a busy machine), so it is woken once half the ring is free again, not
    # for every batch. That cannot leave it waiting for good: a waiting child has sent a full ring, which
    # the parent takes whole.
    every = max(1, len(ring.slots) // 2)
    while True:
        header = stream.read(_HEADER.size)
        body = stream.read(_HEADER.unpack(header)[0]) if len(header) == _HEADER.size else b""
        if not body:
            raise ReaderProcessError("the reader process ended unexpectedly")
        chunk, end, error = pickle.loads(body)
        items = []
        for payload, slot in chunk:
            items.append((payload, None if slot is None else ring.slots[slot].copy()))
            taken += slot is not None
        ring.taken[0] = taken
        if taken - woken >= every:
            woken = taken
            try:
                os.write(wake_w, b"\0")   # wake a child waiting for slots (a full pipe has bytes to wake it)
            except (BlockingIOError, BrokenPipeError):   # bytes are waiting already; the child has finished
                pass
        yield from items
        if error is not None:
            raise error
        if end:
            return
