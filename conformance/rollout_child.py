"""Rollout requests over the JSON-lines protocol, with the field served by the runner ([CR-4]).

Runner side: :class:`RolloutChild` starts an implementation (``--impl-cmd``, or
``python -m softrtc.conformance.rollout_child --impl X`` for a Python one),
sends one ``rollout_chunk`` request at a time and, while the child computes,
answers its field requests from the served checkpoint:

    runner -> child   {"id": N, "function": "rollout_chunk", "args": {...}}
    child -> runner   {"id": N, "field": "velocity", "x": [[...]], "t": [...]}
    runner -> child   {"id": N, "velocity": [[...]]}          (or {"id": N, "error": "why"})
    child -> runner   {"id": N, "field": "vjp", "x": ..., "t": ..., "cotangent": ...}
    runner -> child   {"id": N, "vjp": [[...]]}
    child -> runner   {"id": N, "result": {"chunk": [[...]], "executed": [[...]]}}  (or an error of [CF-29])

The hello line is the one of [CF-29] with ``rollout_chunk`` among its
functions. Field requests carry no observation: the field answers for the
observation of the request in flight. Times and velocities are in the time
convention the hello line declares ([V-1]).

Child side (this module run as a program): serves a Python rollout
implementation, its prints on stderr, each field call a round trip on
stdin and stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from . import protocol
from .adapter import AdapterError, _describe
from .protocol import Child, ChildLost, ImplementationError

FUNCTION = "rollout_chunk"


def _json(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


class LacksRolloutChunk(ImplementationError):
    """The implementation started but its hello line does not list ``rollout_chunk`` ([CR-4]): `conformance
    rollout` stops (status 2), `conformance run` counts the rollout cases unsupported ([CR-10])."""


class RolloutChild(Child):
    """An implementation process answering ``rollout_chunk`` with field callbacks ([CR-4])."""

    def start(self) -> None:
        super().start()
        if FUNCTION not in self.functions:
            self.stop()
            raise LacksRolloutChunk(f"the implementation ({self.label}) does not list {FUNCTION} among its "
                                    "functions in its hello line ([CR-4])")

    def call(self, rid: int, args: dict, field, timeout: float) -> dict:
        """One request; field requests are answered from ``field`` (the child's convention) until the reply.
        Returns the reply dict ({"result": ...} or {"error": ...}); ChildLost when the child fails."""
        text = json.dumps({"id": rid, "function": FUNCTION, "args": {k: _json(v) for k, v in args.items()}},
                          separators=(",", ":"), allow_nan=False)
        self._writes.put((text + "\n").encode("utf-8"))
        deadline = time.monotonic() + timeout
        while True:
            line = self._next(deadline)
            if line is None:
                raise ChildLost("no answer within the request time limit (--case-timeout)")
            if line is protocol._EOF:
                raise ChildLost(f"the implementation's process {self._death()} during this request")
            try:
                msg = protocol.parse_line(line)
            except ValueError:
                msg = None
            if not isinstance(msg, dict) or msg.get("id") != rid:
                raise ChildLost(f"protocol error: the child wrote {line[:80]!r}, not a reply to request {rid}")
            if "field" in msg:
                self._writes.put((self._field_reply(rid, msg, args["obs"], field) + "\n").encode("utf-8"))
                continue
            if ("result" in msg) == ("error" in msg):
                raise ChildLost(f"protocol error: the child wrote {line[:80]!r}, not a reply ([CF-29])")
            return msg

    @staticmethod
    def _field_reply(rid: int, msg: dict, obs, field) -> str:
        kind = msg.get("field")
        try:
            if kind == "velocity":
                out = {"velocity": field(obs, np.asarray(msg["x"], np.float64), np.asarray(msg["t"], np.float64))}
            elif kind == "vjp":
                out = {"vjp": field.vjp(obs, np.asarray(msg["x"], np.float64), np.asarray(msg["t"], np.float64),
                                        np.asarray(msg["cotangent"], np.float64))}
            else:
                raise ValueError(f"field must be 'velocity' or 'vjp', got {kind!r}")
        except (ValueError, KeyError, TypeError) as exc:
            return json.dumps({"id": rid, "error": f"field request refused: {_describe(exc)}"})
        return json.dumps({"id": rid, **{k: v.tolist() for k, v in out.items()}}, separators=(",", ":"))


class RemoteField:
    """The child's view of the served field: each call one round trip to the runner ([CR-4])."""

    def __init__(self, rid, out, stdin):
        self.rid, self.out, self.stdin = rid, out, stdin

    def _ask(self, msg: dict, key: str) -> np.ndarray:
        self.out.write(json.dumps({"id": self.rid, **msg}, separators=(",", ":")) + "\n")
        self.out.flush()
        reply = json.loads(self.stdin.readline() or b"{}")
        if key not in reply:
            raise ValueError(str(reply.get("error", "the runner closed the protocol during a field request")))
        return np.asarray(reply[key], np.float64)

    def __call__(self, obs, x, t):
        return self._ask({"field": "velocity", "x": np.asarray(x, np.float64).tolist(),
                          "t": np.broadcast_to(np.asarray(t, np.float64), np.shape(x)[:1]).tolist()}, "velocity")

    def vjp(self, obs, x, t, cotangent):
        return self._ask({"field": "vjp", "x": np.asarray(x, np.float64).tolist(),
                          "t": np.broadcast_to(np.asarray(t, np.float64), np.shape(x)[:1]).tolist(),
                          "cotangent": np.asarray(cotangent, np.float64).tolist()}, "vjp")


ARRAYS = ("obs", "prev", "noise")


def _error(rid, exc: BaseException) -> dict:
    kind = "invalid_input" if isinstance(exc, ValueError) else \
        "unsupported" if isinstance(exc, NotImplementedError) else "exception"
    return {"id": rid, "error": {"kind": kind, "type": type(exc).__name__, "message": str(exc)[:500]}}


def serve(impl: str, stdin, out) -> int:
    """Load the rollout implementation ``impl``, write the hello line, answer requests until stdin closes."""
    from .rollout_impls import NoRolloutChunk, impl_methods, load_rollout_impl

    def send(obj: dict) -> None:
        out.write(json.dumps(obj, separators=(",", ":"), allow_nan=False) + "\n")
        out.flush()

    try:
        impl_obj = load_rollout_impl(impl)
    except NoRolloutChunk as exc:  # it loads but has no rollout_chunk: a hello listing no function ([CR-4])
        name = getattr(exc.adapter, "name", None)
        tc = getattr(exc.adapter, "time_convention", "data_at_1")
        send(protocol.hello(name if isinstance(name, str) and name else impl,
                            tc if tc in ("data_at_1", "noise_at_1") else "data_at_1", []))
        for raw in iter(stdin.readline, b""):
            send({"id": None, "error": {"kind": "unsupported", "message": f"no {FUNCTION}"}})
        return 0
    except (AdapterError, ValueError, ImportError) as exc:
        send(protocol.hello_error(f"cannot load rollout implementation {impl!r}: {_describe(exc)}"))
        return 2
    hello = protocol.hello(impl_obj.name, getattr(impl_obj, "time_convention", "data_at_1"), [FUNCTION])
    send(dict(hello, methods=list(impl_methods(impl_obj))))
    remote = RemoteField(None, out, stdin)  # one object for every request: an implementation may cache it
    for raw in iter(stdin.readline, b""):
        try:
            msg = protocol.parse_line(raw)
            rid, args = msg["id"], dict(msg["args"])
        except (ValueError, KeyError, TypeError) as exc:
            send({"id": None, "error": {"kind": "bad_call", "message": f"unreadable request: {_describe(exc)}"}})
            continue
        for k in ARRAYS:
            if args.get(k) is not None:
                args[k] = np.asarray(args[k], np.float64)
        try:
            remote.rid = rid
            res = impl_obj.rollout_chunk(remote, args["obs"], args["prev"], args["noise"],
                                         args["method"], args["s"], args["d"], args["arrival"], args["T"],
                                         args["window"], args["max_guidance"])
            result = {k: np.asarray(res[k], np.float64).tolist() for k in ("chunk", "executed")}
            send({"id": rid, "result": result})
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # noqa: BLE001 - every failure of the implementation is a reply
            send(_error(rid, exc))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.rollout_child",
                                     description="Serve a Python rollout implementation over the protocol ([CR-4]).")
    parser.add_argument("--impl", required=True, help="built-in rollout implementation, module[:ATTR] or file.py")
    args = parser.parse_args(argv)
    from .host import protocol_stdout

    return serve(args.impl, sys.stdin.buffer, protocol_stdout())


if __name__ == "__main__":
    sys.exit(main())
