"""The Python end of the child-process protocol ([CF-29]): serves one Python adapter to the runner.

    python -m softrtc.conformance.host --impl NAME_OR_MODULE:ATTR

The runner starts this program for ``--impl`` (the default, isolated mode).
It loads the adapter, writes the hello line, then answers one request per line
on stdin, in order, until stdin closes. Whatever the adapter prints goes to
stderr, so stdout carries protocol lines only. The runner reads the vectors,
compares and reports; nothing the adapter does here can change a verdict.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from . import protocol
from .adapter import AdapterError, _describe, load_adapter
from .invoke import BadResult, Invoker, to_json
from .vectors_io import parse_json


def _encode(reply: dict) -> str:
    if "result" in reply:
        try:
            reply = dict(reply, result={k: to_json(v) for k, v in reply["result"].items()})
            return json.dumps(reply, allow_nan=False, separators=(",", ":"))
        except (BadResult, TypeError, ValueError) as exc:
            reply = {"id": reply.get("id"), "error": {"kind": "bad_result", "message": str(exc)[:300]}}
    return json.dumps(reply, allow_nan=False, separators=(",", ":"), default=str)


def serve(impl: str, stdin, out) -> int:
    """Load ``impl``, write the hello line to ``out`` and answer requests from ``stdin`` until it closes."""
    def send(obj: dict | str) -> None:
        out.write((obj if isinstance(obj, str) else json.dumps(obj, separators=(",", ":"))) + "\n")
        out.flush()

    try:
        inv = Invoker(load_adapter(impl))
    except AdapterError as exc:
        send(protocol.hello_error(str(exc)))
        return 2
    send(protocol.hello(inv.name, inv.time_convention, inv.functions))
    for raw in iter(stdin.readline, b""):
        try:
            msg = parse_json(raw.decode("utf-8"), checked=False)  # the runner checked every number ([CF-28])
            rid, attr, args = msg["id"], msg["function"], msg["args"]
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            send({"id": None, "error": {"kind": "bad_call", "message": f"unreadable request: {_describe(exc)}"}})
            continue
        reply = inv.call(attr, args)
        reply["id"] = rid
        send(_encode(reply))
    return 0


def protocol_stdout():
    """The process's stdout as a text stream for protocol lines alone: file descriptor 1 and ``sys.stdout`` then
    point to stderr, so whatever the implementation prints cannot corrupt the protocol ([CF-29])."""
    out = os.fdopen(os.dup(1), "w", encoding="utf-8", newline="\n")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.host",
                                     description="Serve a Python adapter over the conformance protocol ([CF-29]).")
    parser.add_argument("--impl", required=True, help="built-in adapter, module[:ATTR] or path/file.py[:ATTR]")
    args = parser.parse_args(argv)
    return serve(args.impl, sys.stdin.buffer, protocol_stdout())


if __name__ == "__main__":
    sys.exit(main())
