"""A fake UR controller on a loopback address that greets and then goes silent (loopback only).

On the RTDE port (30004) it answers the first package, the protocol-version request, with "accepted",
then reads and never answers again; on the dashboard port (29999) it sends the welcome line, then
nothing; the script ports (30001-30003) accept and stay silent. Every probe of the start-up check
passes, and ur_rtde's constructors then wait for ever: the half-alive robot of issue #29. It runs in
a process of its own (ur_rtde's constructors hold the GIL of the process they run in).
"""
from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

HALF_ALIVE_SERVER = r'''
import socket, struct, sys, threading
host = sys.argv[1]
held = []
def rtde(conn):
    try:
        size, kind = struct.unpack(">HB", conn.recv(3, socket.MSG_WAITALL))
        conn.recv(size - 3, socket.MSG_WAITALL)
        if kind == ord("V"):
            conn.sendall(struct.pack(">HBB", 4, ord("V"), 1))   # protocol version accepted
        while conn.recv(4096):   # and then nothing, ever
            pass
    except OSError:
        pass
def dashboard(conn):
    try:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        while conn.recv(4096):
            pass
    except OSError:
        pass
def silent(conn):
    held.append(conn)
def serve(server, handler):
    while True:
        conn, _ = server.accept()
        threading.Thread(target=handler, args=(conn,), daemon=True).start()
for port, handler in ((30004, rtde), (29999, dashboard), (30001, silent), (30002, silent), (30003, silent)):
    server = socket.socket(); server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((host, port)); server.listen(16)
    threading.Thread(target=serve, args=(server, handler), daemon=True).start()
print("listening", flush=True)
threading.Event().wait()
'''


@contextmanager
def half_alive_ur_host(subnet: int = 2) -> Iterator[str]:
    """A free 127.0.<subnet>.x running HALF_ALIVE_SERVER; the server is killed on exit. RuntimeError when
    no address of the subnet is free."""
    for attempt in range(10):
        host = f"127.0.{subnet}.{(os.getpid() + 29 * attempt) % 250 + 1}"
        server = subprocess.Popen([sys.executable, "-u", "-c", HALF_ALIVE_SERVER, host], stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True)
        assert server.stdout is not None
        if server.stdout.readline().strip() == "listening":
            break
        server.wait(timeout=5)
    else:
        raise RuntimeError("no free loopback address for the half-alive UR host")
    try:
        yield host
    finally:
        server.kill()
        server.wait(timeout=5)
