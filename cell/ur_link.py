"""Calls into ur_rtde with a deadline each.

A UR controller that accepts a connection and then goes silent makes ur_rtde block for
ever, and its constructors do so while holding the GIL (dependencies.md): no thread of
the calling process can even notice. So the real link, :class:`ProcessLink`, keeps the
three ur_rtde interfaces in a child process and waits for each answer with a deadline;
past it the child is killed, which closes its sockets. :class:`ThreadLink` runs the calls
on a worker thread of this process instead: for ur_rtde stand-ins that live in this
process (the tests' fakes), whose blocking calls release the GIL.

Every failure is one of three exceptions: :class:`LinkTimeout` (no answer within the
deadline; the link is dead), :class:`LinkLost` (the child died or the pipe broke; the
link is dead) and :class:`LinkCallError` (ur_rtde raised, e.g. a dropped RTDE connection;
the link itself still works). None of them is a TapecellError: :class:`cell.ur.URArm`
turns them into one line for the user after trying to stop the arm.
"""
from __future__ import annotations

import importlib
import multiprocessing as mp
import queue
import sys
import threading
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, Sequence

RTDE_MODULES = (("receive", "rtde_receive", "RTDEReceiveInterface"),
                ("control", "rtde_control", "RTDEControlInterface"),
                ("io", "rtde_io", "RTDEIOInterface"))
"""(interface name, module, class), in the order they are constructed."""
CLOSE_ORDER = ("control", "receive", "io")
"""The order they are disconnected."""


class LinkTimeout(Exception):
    """No answer within the deadline; the link is dead (its child killed or its thread abandoned)."""


class LinkLost(Exception):
    """The link's process died or its pipe broke; the link is dead."""


class LinkCallError(Exception):
    """ur_rtde raised (``kind`` is the exception's type name); the link still works."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def _construct(host: str, modules: Sequence[tuple[str, str, str]]) -> dict[str, Any]:
    """The ur_rtde interfaces, constructed in order; the ones made are closed if one fails."""
    made: dict[str, Any] = {}
    try:
        for name, module, cls in modules:
            made[name] = getattr(importlib.import_module(module), cls)(host)
    except BaseException:
        _close(made)
        raise
    return made


def _close(interfaces: dict[str, Any]) -> None:
    for name in CLOSE_ORDER:
        iface = interfaces.get(name)
        if iface is not None:
            try:
                iface.disconnect()
            except Exception:  # noqa: BLE001 - already gone; nothing else to release
                pass


def _error(e: BaseException) -> tuple[str, str, str]:
    return ("err", type(e).__name__, str(e))


# ------------------------------------------------------------------------------- process
def _serve(conn, modules: Sequence[tuple[str, str, str]], extra_path: Sequence[str]) -> None:
    """The child: construct on "open", run "call"s, close on "close" or a closed pipe."""
    sys.path[:0] = list(extra_path)
    interfaces: dict[str, Any] = {}
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            try:
                if msg[0] == "open":
                    interfaces = _construct(msg[1], modules)
                    reply: tuple = ("ok", None)
                elif msg[0] == "call":
                    _, iface, method, args = msg
                    reply = ("ok", getattr(interfaces[iface], method)(*args))
                elif msg[0] == "close":
                    _close(interfaces)
                    interfaces = {}
                    conn.send(("ok", None))
                    return
                else:
                    reply = ("err", "ValueError", f"unknown request {msg[0]!r}")
            except Exception as e:  # noqa: BLE001 - every ur_rtde error goes back to the caller
                reply = _error(e)
            conn.send(reply)
    finally:
        _close(interfaces)


class ProcessLink:
    """ur_rtde in a child process (spawned: no inherited threads or GL contexts).

    modules: (interface, module, class) to construct; extra_path: folders put first on the
    child's ``sys.path`` (for stand-in modules in tests)."""

    def __init__(self, modules: Sequence[tuple[str, str, str]] = RTDE_MODULES,
                 extra_path: Sequence[str] = ()) -> None:
        self.modules, self.extra_path = tuple(modules), tuple(str(p) for p in extra_path)
        self._proc = self._conn = None
        self.dead = False

    def open(self, host: str, timeout: float) -> None:
        self.dead = False
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, self.modules, self.extra_path),
                                 name="tapecell-ur-link", daemon=True)
        self._proc.start()
        child.close()
        self._request(("open", host), timeout)

    def call(self, iface: str, method: str, *args: Any, timeout: float) -> Any:
        return self._request(("call", iface, method, args), timeout)

    def _request(self, msg: tuple, timeout: float) -> Any:
        if self.dead or self._conn is None:
            raise LinkLost("the link to the robot is closed")
        try:
            self._conn.send(msg)
            ready = self._conn.poll(timeout)
        except (OSError, EOFError) as e:
            self.kill()
            raise LinkLost(f"the link process is gone ({e})") from None
        except BaseException:
            self.kill()     # interrupted while the child works: its answer would come out of turn
            raise
        if not ready:
            self.kill()
            raise LinkTimeout(f"no answer within {timeout:g} s")
        try:
            reply = self._conn.recv()
        except (OSError, EOFError):
            self.kill()
            raise LinkLost("the link process died") from None
        if reply[0] == "err":
            raise LinkCallError(reply[1], reply[2])
        return reply[1]

    def close(self, timeout: float = 2.0) -> None:
        """Disconnect the interfaces and end the child, within ``timeout`` (else kill it)."""
        if self._proc is None:
            return
        if not self.dead:
            try:
                self._conn.send(("close",))
                self._conn.poll(timeout)
            except (OSError, EOFError):
                pass
        self._proc.join(0.5)
        self.kill()

    def kill(self) -> None:
        """End the child now (its sockets close with it); the link is dead."""
        self.dead = True
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2.0)
        if self._conn is not None:
            self._conn.close()
            self._conn = None


# -------------------------------------------------------------------------------- thread
class ThreadLink:
    """ur_rtde (or a stand-in) in this process, each call run on one worker thread and
    waited for with a deadline. Past a deadline the worker is abandoned (a daemon thread)
    and the link is dead. Only sound for modules whose blocking calls release the GIL."""

    def __init__(self, modules: Sequence[tuple[str, str, str]] = RTDE_MODULES) -> None:
        self.modules = tuple(modules)
        self._jobs: queue.Queue = queue.Queue()
        self._interfaces: dict[str, Any] = {}
        self._thread: threading.Thread | None = None
        self.dead = False

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            future, fn = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as e:  # noqa: BLE001 - handed to the waiting caller
                future.set_exception(e)

    def _run(self, fn, timeout: float) -> Any:
        if self.dead:
            raise LinkLost("the link to the robot is closed")
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name="tapecell-ur-link", daemon=True)
            self._thread.start()
        future: Future = Future()
        self._jobs.put((future, fn))
        try:
            return future.result(timeout)
        except FutureTimeout:
            self.kill()
            raise LinkTimeout(f"no answer within {timeout:g} s") from None
        except Exception as e:  # noqa: BLE001 - what ur_rtde raised
            raise LinkCallError(type(e).__name__, str(e)) from None
        except BaseException:
            if not future.done():
                self.kill()  # interrupted while the worker is busy: it is abandoned
            raise

    def open(self, host: str, timeout: float) -> None:
        self.dead = False
        self._jobs = queue.Queue()

        def construct():
            self._interfaces = _construct(host, self.modules)
        self._run(construct, timeout)

    def call(self, iface: str, method: str, *args: Any, timeout: float) -> Any:
        return self._run(lambda: getattr(self._interfaces[iface], method)(*args), timeout)

    def close(self, timeout: float = 2.0) -> None:
        if self._thread is None or self.dead:
            self.kill()
            return
        try:
            self._run(lambda: _close(self._interfaces), timeout)
        except (LinkTimeout, LinkLost, LinkCallError):
            pass
        self.kill()

    def kill(self) -> None:
        self.dead = True
        if self._thread is not None:
            self._jobs.put(None)   # ends the worker if it is free; a stuck one stays abandoned
            self._thread = None
