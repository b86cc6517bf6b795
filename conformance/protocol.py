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
child's stdin at the end and the child exits. The child runs in a process group
of its own, which is killed whenever the child is stopped ([CF-35]); of its
stderr only the last STDERR_TAIL bytes are kept ([CF-36]); its address space
can be limited ([CF-37]).
"""

from __future__ import annotations

import json
import os
import queue
import re
import resource
import signal
import subprocess
import threading
import time
from collections import deque

from .adapter import TIME_CONVENTIONS, AdapterError

PROTOCOL = "softrtc-conformance"
VERSION = 1
ERROR_KINDS = ("invalid_input", "unsupported", "exception", "bad_result", "bad_call")
# Bytes of the child's stderr kept for messages: a failure quotes the last line, and an adapter that prints
# in a loop must not fill the disk or the runner's memory ([CF-36]).
STDERR_TAIL = 64 * 1024
# Seconds a line may still arrive after the child exited: its last replies can be in the pipe, but a
# grandchild holding the pipe open must not turn an exit into a time-out ([CF-35]).
EXIT_GRACE = 0.5
# Seconds between looks at whether the child still runs while waiting for a line.
POLL = 0.1


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
# How programs say they ran out of memory on their last stderr line: Python's MemoryError, C++'s
# std::bad_alloc, glibc's and Node's messages ([CF-37]).
_OUT_OF_MEMORY = re.compile(r"MemoryError|bad_alloc|out of memory|cannot allocate memory", re.I)


def parse_line(line: bytes):
    """One protocol line as a Python value. ValueError for a line that is no JSON, including one nested
    deeper than Python's parser follows (RecursionError) or too large to parse (MemoryError): whatever the
    child writes ends in one line, never a traceback ([CF-18], [CF-29])."""
    try:
        return json.loads(line)
    except RecursionError:
        raise ValueError("JSON nested too deeply to parse") from None
    except MemoryError:
        raise ValueError("a line too large to parse") from None


class Tail:
    """The last ``limit`` bytes of a stream ([CF-36]): chunks are appended and the oldest dropped, so the
    memory held never exceeds ``limit`` plus one chunk, whatever the stream's length."""

    def __init__(self, limit: int = STDERR_TAIL):
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"limit must be an int >= 1 (bytes), got {limit!r}")
        self.limit, self._chunks, self._size = limit, deque(), 0
        self._lock = threading.Lock()

    def add(self, chunk: bytes) -> None:
        with self._lock:
            self._chunks.append(bytes(chunk))
            self._size += len(chunk)
            while self._size - len(self._chunks[0]) >= self.limit:
                self._size -= len(self._chunks.popleft())

    def bytes(self) -> bytes:
        """The kept tail: at most ``limit`` bytes, the stream's last."""
        with self._lock:
            return b"".join(self._chunks)[-self.limit:]


def _memory_limiter(megabytes: int | None):
    """A preexec_fn limiting the child's address space to ``megabytes`` MB ([CF-37]); None for no limit.
    It runs between fork and exec, so it only calls setrlimit (no allocation, no lock)."""
    if megabytes is None:
        return None
    limit = int(megabytes) * 1024 * 1024

    def limit_memory():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return limit_memory


class Child:
    """One implementation process: started by :meth:`start`, replaced by a fresh one with :meth:`restart`.
    ``memory_mb``: the limit of its address space in MB ([CF-37]), None for none."""

    def __init__(self, argv: list, start_timeout: float, label: str, memory_mb: int | None = None):
        self.argv, self.start_timeout, self.label = list(argv), float(start_timeout), label
        self.memory_mb = memory_mb
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
        try:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, start_new_session=True,
                                         preexec_fn=_memory_limiter(self.memory_mb))
        except (OSError, subprocess.SubprocessError) as exc:
            raise ImplementationError(f"cannot start the implementation ({self.label}): {exc}") from None
        self._lines: queue.Queue = queue.Queue()
        self._writes: queue.Queue = queue.Queue()
        self._err = Tail()
        self._err_reader = threading.Thread(target=self._drain, args=(self.proc.stderr, self._err), daemon=True)
        self._err_reader.start()
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
            msg = parse_line(line)
        except ValueError as exc:
            self.stop()
            raise ImplementationError(f"the implementation ({self.label}) did not start with a {PROTOCOL} hello "
                                      f"line; it wrote {line[:40]!r}..., not readable JSON: {exc} ([CF-29])") from None
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
        """End the child: close its stdin, give it a moment to exit, then kill its process group, whether or
        not the child itself has exited: processes it started must not outlive the case ([CF-35])."""
        if self.proc is None:
            return
        proc, self.proc = self.proc, None
        self._writes.put(None)
        try:
            proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            pass
        try:
            # The group keeps the child's id while any member lives, even after the child was reaped.
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        if proc.poll() is None:
            proc.kill()
        proc.wait()

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
            msg = parse_line(line)
        except ValueError as exc:
            msg, why = None, f" ({exc})"
        else:
            why = ""
        if not isinstance(msg, dict) or "id" not in msg or ("result" in msg) == ("error" in msg):
            raise ChildLost(f"protocol error: the child wrote {line[:80]!r}{why}, not a reply ([CF-29])")
        # Values of a reply without JSON booleans may be compared as parsed: Python's True == 1 cannot occur.
        msg["_no_booleans"] = b"true" not in line and b"false" not in line
        return msg

    def _next(self, deadline: float):
        """The next line, _EOF, or None at ``deadline``. A child that exited ends the wait EXIT_GRACE seconds
        later with _EOF even when a process it started keeps the pipe open ([CF-35])."""
        exited = None
        while True:
            now = time.monotonic()
            end = deadline if exited is None else min(deadline, exited + EXIT_GRACE)
            try:
                return self._lines.get(timeout=max(0.0, min(end - now, POLL)))
            except queue.Empty:
                pass
            now = time.monotonic()
            if exited is None and self.proc is not None and self.proc.poll() is not None:
                exited = now
            elif exited is not None and now >= exited + EXIT_GRACE:
                return _EOF
            if now >= deadline:
                return None

    def _death(self) -> str:
        try:
            rc = self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            return "closed its output"
        self._err_reader.join(timeout=EXIT_GRACE)  # what the child wrote last, unless a grandchild holds the pipe
        tail = [ln for ln in self._err.bytes()[-4000:].decode("utf-8", "replace").splitlines() if ln.strip()]
        how = f"exited with status {rc}"
        if rc < 0:
            try:
                how = f"was killed by signal {-rc} ({signal.Signals(-rc).name})"
            except ValueError:
                how = f"was killed by signal {-rc}"
        last = tail[-1].strip()[:200] if tail else ""
        # A child that died of its memory limit says so in its own words; the message names the limit ([CF-37]).
        limit = f" under the memory limit of {self.memory_mb} MB (--case-memory-mb)" \
            if self.memory_mb is not None and _OUT_OF_MEMORY.search(last) else ""
        return how + (f" (last stderr line: {last})" if last else "") + limit

    @staticmethod
    def _drain(stream, tail: Tail) -> None:
        """Read the child's stderr to its end, keeping the tail ([CF-36])."""
        try:
            for chunk in iter(lambda: stream.read1(65536), b""):
                tail.add(chunk)
        except (OSError, ValueError):
            pass
        finally:
            try:
                stream.close()
            except OSError:
                pass

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

