"""An encoder run in a child process, so its Python work never holds the
interpreter lock the control loop needs.

A record's encoder (:class:`companion.records.writer.Encoder`) runs on the
writer's thread, but a thread running Python holds the one interpreter lock:
a sample that arrives while it formats waits for it. :class:`ProcessEncoder`
hands each batch to the same encoder in a child process
(``python -m companion.records._encoder_child``) and waits for the bytes with
the lock released. The writer's thread still writes the file, so a full disk,
a killed companion or a stalled write behave as with an encoder in the thread.

The child is started at the first batch, off the control path; if it cannot
start, the encoder in this process takes over (nothing was encoded yet, so the
file is the same). Once it has encoded, a child that ends or fails stops the
record, as a write error does: the flight goes on. The child ends when its
input closes (at :meth:`ProcessEncoder.finish`, or when this process ends, even
on a ``kill -9``).

Frames on the child's stdin and stdout: an 8-byte little-endian length, then a
pickle: ``("init", "module:factory", args)``, ``("encode", data)``,
``("finish",)``; each answered by ``("ok", bytes)`` or ``("error", text)``.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import pickle
import struct
import subprocess
import sys
from typing import IO, Any

from companion.records.writer import Encoder

__all__ = ["ProcessEncoder", "serve"]

log = logging.getLogger("companion.records")

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


class ProcessEncoder:
    """``local``'s twin, ``factory(*args)``, encoding in a child process (module
    docstring). ``local`` gives the header at once and encodes in this process
    if the child cannot start."""

    def __init__(self, factory: str, args: tuple[Any, ...], local: Encoder) -> None:
        self._factory = factory
        self._args = args
        self._local = local
        self._proc: subprocess.Popen[bytes] | None = None
        self._in_process = False
        """The child could not start: ``local`` encodes."""

    def __del__(self) -> None:
        # A file that failed is never finished: its child ends with its encoder.
        with contextlib.suppress(Exception):
            self._end()

    @property
    def pid(self) -> int | None:
        """The child's process id, once started."""
        return None if self._proc is None else self._proc.pid

    def encode(self, data: Any) -> bytes:
        if self._proc is None and not self._in_process:
            self._start()
        if self._in_process:
            return self._local.encode(data)
        return self._call(("encode", data))

    def finish(self) -> bytes:
        if self._proc is None:
            return self._local.finish()
        try:
            return self._call(("finish",))
        finally:
            self._end()

    # ------------------------------------------------------------------ the child
    def _start(self) -> None:
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "companion.records._encoder_child"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
        except OSError as exc:
            log.warning("records: the encoder's process did not start (%s); encoding here", exc)
            self._in_process = True
            return
        self._proc = proc
        try:
            self._call(("init", self._factory, self._args))
        except OSError as exc:
            log.warning("records: the encoder's process did not start (%s); encoding here", exc)
            self._proc = None
            self._in_process = True

    def _call(self, request: tuple[Any, ...]) -> bytes:
        """The child's answer to ``request``; OSError (and the child ended) if none."""
        proc = self._proc
        assert proc is not None and proc.stdin is not None and proc.stdout is not None
        try:
            _send(proc.stdin, request)
            reply = _recv(proc.stdout)
        except (OSError, ValueError, pickle.PicklingError) as exc:
            self._end()
            raise OSError(f"the encoder's process: {exc}") from exc
        if reply is None:
            code = self._end()
            raise OSError(f"the encoder's process ended (exit code {code})")
        status, payload = reply
        if status != "ok":
            self._end()
            raise OSError(f"the encoder's process failed: {payload}")
        return bytes(payload)

    def _end(self) -> int | None:
        """Close the child's input, wait for it a moment, then kill it; its exit code."""
        proc = self._proc
        if proc is None:
            return None
        if proc.returncode is not None:
            return proc.returncode
        for pipe in (proc.stdin, proc.stdout):
            with contextlib.suppress(OSError):
                if pipe is not None:
                    pipe.close()
        try:
            return proc.wait(_END_WAIT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()


def serve(inp: IO[bytes], out: IO[bytes]) -> int:
    """The child's loop: build the encoder, then answer each request."""
    encoder: Any = None
    while True:
        request = _recv(inp)
        if request is None:
            return 0
        kind = request[0]
        try:
            if kind == "init":
                module, name = request[1].split(":")
                encoder = getattr(importlib.import_module(module), name)(*request[2])
                header = getattr(encoder, "header", None)
                if header is not None:
                    header()  # the parent's twin wrote it already
                _send(out, ("ok", b""))
            elif kind == "encode":
                _send(out, ("ok", encoder.encode(request[1])))
            elif kind == "finish":
                _send(out, ("ok", encoder.finish()))
                return 0
            else:
                _send(out, ("error", f"unknown request {kind!r}"))
        except Exception as exc:  # reported; the parent stops the record
            _send(out, ("error", f"{type(exc).__name__}: {exc}"))
            return 1
