"""An object living in a child process, called over a pipe.

A thread of the companion's that runs Python holds the interpreter's one lock,
and an IMU sample that arrives meanwhile waits for it. Work that formats
thousands of messages a second (the control log's MCAP, the live view's JSON)
therefore runs in a child process instead (:class:`ChildObject`), and the
thread that hands it the work waits for the answer with the lock released.

The child is ``python -m companion._child`` (:func:`serve`): it builds
``factory(*args)`` and answers each call on it. Frames on its stdin and stdout:
an 8-byte little-endian length, then a pickle: ``("init", "module:factory",
args)``, then ``("call", method, args)`` any number of times, each answered by
``("ok", result)`` or ``("error", text)``. The child ends when its input closes:
at :meth:`ChildObject.close`, or when the companion ends, even on a ``kill -9``.
"""

from __future__ import annotations

import contextlib
import importlib
import pickle
import struct
import subprocess
import sys
import threading
from typing import IO, Any

__all__ = ["ChildObject", "serve"]

_LEN = struct.Struct("<Q")
_END_WAIT_S = 2.0


def _send(f: IO[bytes], obj: object) -> None:
    body = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_LEN.pack(len(body)))
    f.write(body)
    f.flush()


def _recv(f: IO[bytes]) -> Any:
    """The next frame's object, or None at the end of the stream."""
    head = f.read(_LEN.size)
    if len(head) < _LEN.size:
        return None
    (n,) = _LEN.unpack(head)
    body = f.read(n)
    if len(body) < n:
        return None
    return pickle.loads(body)  # our own child, over its own pipe


class ChildObject:
    """``factory(*args)`` (``"module:name"``) built in a child process and called there.

    ``nice``: added to the child's niceness (Unix), so that the scheduler gives
    the companion's own threads the CPU first when both want it.

    Raises
    ------
    OSError
        From the constructor if the child cannot start or its object cannot be
        built; from :meth:`call` if the child failed or ended (it is then ended).
    """

    def __init__(self, factory: str, args: tuple[Any, ...], *, nice: int = 0) -> None:
        self._lock = threading.Lock()
        """One exchange at a time: a frame is never interleaved with another's."""
        self._proc: subprocess.Popen[bytes] | None = subprocess.Popen(
            [sys.executable, "-m", "companion._child", str(int(nice))],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        self._exchange(("init", factory, args))

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    @property
    def pid(self) -> int | None:
        """The child's process id; None once it has ended."""
        proc = self._proc
        return None if proc is None or proc.returncode is not None else proc.pid

    def call(self, method: str, *args: Any) -> Any:
        """``method(*args)`` on the child's object: what it returned."""
        return self._exchange(("call", method, args))

    def kill(self) -> None:
        """End the child now, whatever it is doing: a call waiting on it returns
        with :class:`OSError`."""
        proc = self._proc
        if proc is not None and proc.returncode is None:
            with contextlib.suppress(OSError):
                proc.kill()

    def close(self) -> int | None:
        """Close the child's input, wait for it a moment, then kill it; its exit code."""
        proc = self._proc
        if proc is None:
            return None
        if proc.returncode is None:
            for pipe in (proc.stdin, proc.stdout):
                with contextlib.suppress(OSError):
                    if pipe is not None:
                        pipe.close()
            try:
                proc.wait(_END_WAIT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def _exchange(self, request: tuple[Any, ...]) -> Any:
        proc = self._proc
        if proc is None or proc.returncode is not None:
            raise OSError("the child process has ended")
        assert proc.stdin is not None and proc.stdout is not None
        try:
            with self._lock:
                _send(proc.stdin, request)
                reply = _recv(proc.stdout)
        except OSError as exc:  # a broken pipe: the child has gone
            code = self.close()
            raise OSError(f"the child process ended (exit code {code}): {exc}") from exc
        except (ValueError, pickle.PicklingError) as exc:
            self.close()
            raise OSError(f"the child process: {exc}") from exc
        if reply is None:
            code = self.close()
            raise OSError(f"the child process ended (exit code {code})")
        status, payload = reply
        if status != "ok":
            self.close()
            raise OSError(f"the child process failed: {payload}")
        return payload


def serve(inp: IO[bytes], out: IO[bytes]) -> int:
    """The child's loop: build the object, then answer each call on it."""
    obj: Any = None
    while True:
        request = _recv(inp)
        if request is None:
            with contextlib.suppress(Exception):
                getattr(obj, "close", lambda: None)()
            return 0
        try:
            if request[0] == "init":
                module, name = request[1].split(":")
                obj = getattr(importlib.import_module(module), name)(*request[2])
                _send(out, ("ok", None))
            elif request[0] == "call":
                _send(out, ("ok", getattr(obj, request[1])(*request[2])))
            else:
                _send(out, ("error", f"unknown request {request[0]!r}"))
        except Exception as exc:  # reported; the parent ends the child
            _send(out, ("error", f"{type(exc).__name__}: {exc}"))
            return 1
