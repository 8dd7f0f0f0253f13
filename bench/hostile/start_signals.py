"""Hostile probes of a Ctrl-C during a node's start: two SIGINTs (a terminal's Ctrl-C under launch) sent at a
chosen moment of the console script's run, from inside the process so that the moment is exact: inside an
extension module's initialisation, inside the import machinery's own callbacks, and at moments spread over
the whole start (module imports, rclpy.init, the node's construction) up to its first spin."""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from bench.hostile import _kit as kit
from bench.hostile.probe import Probe

SPREAD_MOMENTS = 16   # moments spread evenly over the Python calls of the start, per node

#: script text (stdlib only) defining `initialising_extension()`: the name of the extension module whose
#: initialisation (its loader's create_module / exec_module) is on the stack, or None: where a module imported
#: then is imported by C code that replaces any exception with its own ImportError
INITIALISING_EXTENSION = """
def initialising_extension():
    frame = sys._getframe()
    while frame is not None:
        loader = frame.f_locals.get("self") if frame.f_code.co_name in ("create_module", "exec_module") else None
        if type(loader).__name__ == "ExtensionFileLoader":
            return loader.name
        frame = frame.f_back
    return None
"""

#: `python -c` argv: ENTRY HOW ARG. HOW is `extension` (at the first import an extension module's initialisation
#: makes), `function` (at the first call of the function named ARG in importlib or rclpy), `call` (at the ARG-th
#: Python call of the main thread) or `count` (print the calls made up to the first spin, then exit).
AT_A_MOMENT = """
import atexit, os, signal, sys
entry, how, arg = sys.argv[1], sys.argv[2], sys.argv[3]

def ctrl_c_twice(where):
    print("signalled", where, flush=True)
    os.kill(os.getpid(), signal.SIGINT)
    os.kill(os.getpid(), signal.SIGINT)

""" + INITIALISING_EXTENSION + """
class AtExtensionImport:
    done = False
    def find_spec(self, name, path=None, target=None):
        extension = None if AtExtensionImport.done else initialising_extension()
        if extension:
            AtExtensionImport.done = True
            ctrl_c_twice(f"importing {name} for {extension}")
        return None

calls = 0
def at_call(frame, event, _arg):
    global calls
    if event != "call":
        return
    calls += 1
    code = frame.f_code
    if how == "count" and code.co_name == "spin_once":
        print("calls", calls, flush=True)
        os._exit(0)
    if (how == "call" and calls == int(arg)) or (how == "function" and code.co_name == arg
                                                 and ("importlib" in code.co_filename or "rclpy" in code.co_filename)):
        sys.setprofile(None)
        ctrl_c_twice(f"{code.co_name} ({code.co_filename}:{frame.f_lineno})")

atexit.register(lambda: print("loaded" if f"touchroller_bringup.nodes.{entry}" in sys.modules else "not loaded",
                              flush=True))
from touchroller_bringup import ros_main
if how == "extension":
    sys.meta_path.insert(0, AtExtensionImport())
else:
    sys.setprofile(at_call)
getattr(ros_main, entry)()
"""


def _run(entry: str, how: str, arg: object = "", timeout: float = 90.0) -> subprocess.CompletedProcess:
    """The node's console entry with two SIGINTs at the moment; SIGKILL if it outlives `timeout`."""
    process = subprocess.Popen([sys.executable, "-c", AT_A_MOMENT, entry, how, str(arg)], cwd=kit._NEUTRAL,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=dict(kit._env(), PYTHONUNBUFFERED="1"))
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGKILL)
        out, err = process.communicate()
        return subprocess.CompletedProcess(process.args, -999, out, err + f"\nstill running after {timeout:g} s")
    return subprocess.CompletedProcess(process.args, process.returncode, out, err)


def _clean(done: subprocess.CompletedProcess, loaded: str | None = None) -> str | None:
    """None when the run was signalled and ended with exit 0, no traceback (nor "Exception ignored"), and the
    node's module `loaded` or `not loaded` as asked."""
    lines = done.stdout.split("\n")
    signalled = next((line for line in lines if line.startswith("signalled")), None)
    if signalled is None:
        return f"never signalled (exit {done.returncode})"
    if done.returncode != 0 or "Traceback" in done.stderr or "Exception ignored" in done.stderr:
        last = [line for line in done.stderr.strip().splitlines() if line.strip()][-1:] or ["no stderr"]
        return f"{signalled}: exit {done.returncode}, {last[0].strip()[:160]}"
    if loaded is not None and loaded not in lines:
        return f"{signalled}: the node's module {'did not load' if loaded == 'loaded' else 'loaded'}"
    return None


def _at(entry: str, how: str, arg: str, loaded: str | None):
    def check(_scratch: Path) -> str | None:
        return _clean(_run(entry, how, arg), loaded)
    return check


def _spread(entry: str):
    """Two SIGINTs at SPREAD_MOMENTS moments spread evenly over the start's Python calls."""
    def check(_scratch: Path) -> str | None:
        counted = _run(entry, "count", timeout=120)
        total = next((int(line.split()[1]) for line in counted.stdout.splitlines() if line.startswith("calls")), 0)
        if total <= 0:
            return f"the start was not counted (exit {counted.returncode}): {counted.stderr.strip()[-160:]}"
        failures = [f"call {n} of {total}: {why}" for n in
                    (total * k // (SPREAD_MOMENTS + 1) for k in range(1, SPREAD_MOMENTS + 1))
                    if (why := _clean(_run(entry, "call", n))) is not None]
        return "; ".join(failures[:3]) + (f" (and {len(failures) - 3} more)" if len(failures) > 3 else "") or None
    return check


def probes() -> list[Probe]:
    P = Probe
    ends_there = "exit 0, no traceback, the node's module never loads"
    return [
        P("Ctrl-C twice while an extension module initialises (sweep_node; numpy imports datetime)", "signals",
          ends_there, _at("sweep_node", "extension", "", "not loaded")),
        P("Ctrl-C twice in the import machinery's module-lock callback (sweep_node)", "signals", ends_there,
          _at("sweep_node", "function", "cb", "not loaded")),
        P("Ctrl-C twice in rclpy.init (sweep_node)", "signals", "exit 0, no traceback",
          _at("sweep_node", "function", "init", "loaded")),
        *(P(f"Ctrl-C twice at {SPREAD_MOMENTS} moments of {entry}'s start", "signals", "exit 0 and no traceback "
            "every time", _spread(entry)) for entry in ("sweep_node", "camera_node")),
    ]

