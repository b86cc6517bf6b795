"""The runner's end of the child-process protocol ([CF-29]..[CF-31]): start an implementation, talk to it in
JSON lines, and notice when it dies, hangs or breaks the protocol.

Messages (one JSON object per line, UTF-8):

  child -> runner, first line  {"protocol": "softrtc-conformance", "version": 1, "name": ...,
                                "time_convention": "data_at_1" | "noise_at_1", "functions": [...]}
                               or {"protocol": ..., "version": 1, "error": "why it cannot serve"}
  runner -> child              {"id": N, "function": NAME, "args": {ARG: VALUE, ...}}
  child -> runner              {"id": N, "result": {OUTPUT: VALUE, ...}}
                               or {"id": N, "error": {"kind": KIND, "type": ..., "message": ..., "where": ...}}

The child answers requests in the order they arrive; the runner closes the
child's stdin at the end and the child exits.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import tempfile
import threading
import time

from .adapter import TIME_CONVENTIONS, AdapterError

PROTOCOL = "softrtc-conformance"
VERSION = 1
ERROR_KINDS = ("invalid_input", "unsupported", "exception", "bad_result", "bad_call")


def hello(name: str, time_convention: str, functions: list) -> dict:
    """The child's first line ([CF-29])."""
    return {"protocol": PROTOCOL, "version": VERSION, "name": name, "time_convention": time_convention,
            "functions": list(functions)}


def hello_error(message: str) -> dict:
    """The first line of a child that cannot serve (its adapter does not load): the run stops, status 2."""
    return {"protocol": PROTOCOL, "version": VERSION, "error": message}


class ImplementationError(AdapterError):
    """The implementation's child process cannot be started or never answers; the run stops ([CF-30])."""


class ChildLost(Exception):
    """The child died, gave no answer in time, or wrote something that is not a reply; one line ([CF-30])."""


_EOF = object()


class Child:
    """One implementation process: started by :meth:`start`, replaced by a fresh one with :meth:`restart`."""

    def __init__(self, argv: list, start_timeout: float, label: str):
        self.argv, self.start_timeout, self.label = list(argv), float(start_timeout), label
        self.proc = None
        self._fields: dict = {}
        self.name = self.time_convention = None
        self.functions: list = []

    # -- life cycle
    def start(self) -> None:
        self.launch()
        self.ready()

    def launch(self) -> None:
        """Start the process without waiting for its hello line (the runner reads the vectors meanwhile)."""
        self._err = tempfile.TemporaryFile()
        try:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._err,
                                         start_new_session=True)
        except OSError as exc:
            raise ImplementationError(f"cannot start the implementation ({self.label}): {exc}") from None
        self._lines: queue.Queue = queue.Queue()
        self._writes: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, args=(self.proc.stdout, self._lines), daemon=True).start()
        threading.Thread(target=self._write, args=(self.proc.stdin, self._writes), daemon=True).start()
        self._launched = time.monotonic()

    def ready(self) -> None:
        """Wait for the hello line ([CF-29]); ImplementationError when none comes within start_timeout."""
        line = self._next(self._launched + self.start_timeout)
        if line is None:
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) wrote no hello line within "
                                      f"{self.start_timeout:g} s of starting ([CF-30])")
        if line is _EOF:
            why = self._death()
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) {why} before its hello line ([CF-30])")
        self._hello(line)

    def _hello(self, line: bytes) -> None:
        try:
            msg = json.loads(line)
        except ValueError:
            msg = None
        if not isinstance(msg, dict) or msg.get("protocol") != PROTOCOL:
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) did not start with a "
                                      f"{PROTOCOL} hello line; it wrote {line[:80]!r} ([CF-29])")
        if msg.get("version") != VERSION:
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) speaks protocol version "
                                      f"{msg.get('version')!r}; this runner speaks {VERSION} ([CF-29])")
        if "error" in msg:
            self.stop()
            raise AdapterError(str(msg["error"]))
        name, tc, fns = msg.get("name"), msg.get("time_convention", "data_at_1"), msg.get("functions")
        if not isinstance(name, str) or not name or tc not in TIME_CONVENTIONS or not isinstance(fns, list) \
                or not all(isinstance(f, str) for f in fns):
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) sent a hello line without a name, "
                                      f"a time_convention in {TIME_CONVENTIONS} and a list of functions ([CF-29])")
        self.name, self.time_convention, self.functions = name, tc, fns

    def restart(self) -> None:
        self.stop()
        self.start()

    def stop(self) -> None:
        """End the child: close its stdin, give it a moment to exit, then kill its process group."""
        if self.proc is None:
            return
        proc, self.proc = self.proc, None
        self._writes.put(None)
        try:
            proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            pass
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError, AttributeError):
                proc.kill()
            proc.wait()
        self._err.close()

    # -- messages
    def submit(self, request: dict) -> None:
        """Queue one request; a writer thread sends it, so a child that stops reading never blocks the runner.
        A field's parameters are encoded once per field object (they repeat in every sampler case)."""
        args = request["args"]
        field = args.get("field")
        if isinstance(field, dict):
            text = self._fields.get(id(field))
            if text is None or text[0] is not field:
                text = self._fields[id(field)] = (field, json.dumps(field, separators=(",", ":"), allow_nan=False))
            rest = json.dumps({k: v for k, v in args.items() if k != "field"}, separators=(",", ":"),
                              allow_nan=False)
            args_text = '{"field":' + text[1] + ("," + rest[1:] if len(rest) > 2 else "}")
        else:
            args_text = json.dumps(args, separators=(",", ":"), allow_nan=False)
        line = '{"id":%d,"function":%s,"args":%s}\n' % (request["id"], json.dumps(request["function"]), args_text)
        self._writes.put(line.encode("utf-8"))

    def receive(self, deadline: float) -> dict:
        """The next reply, or ChildLost when the child dies, passes ``deadline`` or writes a non-reply line."""
        line = self._next(deadline)
        if line is None:
            raise ChildLost("no answer within the case time limit (--case-timeout); the child was stopped and "
                            "the run went on in a fresh one")
        if line is _EOF:
            raise ChildLost(f"the implementation's process {self._death()} while running this case; the run "
                            "went on in a fresh one")
        try:
            msg = json.loads(line)
        except ValueError:
            msg = None
        if not isinstance(msg, dict) or "id" not in msg or ("result" in msg) == ("error" in msg):
            raise ChildLost(f"protocol error: the child wrote {line[:80]!r}, not a reply ([CF-29])")
        # Values of a reply without JSON booleans may be compared as parsed: Python's True == 1 cannot occur.
        msg["_no_booleans"] = b"true" not in line and b"false" not in line
        return msg

    def _next(self, deadline: float):
        try:
            return self._lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            return None

    def _death(self) -> str:
        try:
            rc = self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            return "closed its output"
        self._err.seek(0)
        tail = [ln for ln in self._err.read()[-4000:].decode("utf-8", "replace").splitlines() if ln.strip()]
        how = f"exited with status {rc}"
        if rc < 0:
            try:
                how = f"was killed by signal {-rc} ({signal.Signals(-rc).name})"
            except ValueError:
                how = f"was killed by signal {-rc}"
        return how + (f" (last stderr line: {tail[-1].strip()[:200]})" if tail else "")

    @staticmethod
    def _read(stream, lines: queue.Queue) -> None:
        for line in iter(stream.readline, b""):
            lines.put(line)
        lines.put(_EOF)

    @staticmethod
    def _write(stream, writes: queue.Queue) -> None:
        while True:
            item = writes.get()
            if item is None:
                break
            try:
                stream.write(item)
                stream.flush()
            except (OSError, ValueError):
                break
        try:
            stream.close()
        except OSError:
            pass
