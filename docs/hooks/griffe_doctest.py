"""Griffe extension for the API reference: docstring examples (``>>>`` lines and their output) as code.

The docstrings are plain text with doctest examples (tests/test_docstrings.py runs them); rendered as
Markdown, an output line such as ``[0, 2, 4, 5, 5, 5]`` would read as a link reference. Each run of
example lines becomes a fenced ``pycon`` block, and nothing else of the docstring changes.
"""

from __future__ import annotations

import griffe


def fence_examples(text: str) -> str:
    """Wrap each doctest example (a ``>>>`` line, its ``...`` continuations and output) in a code fence.

    A blank line or the end of the docstring ends an example, as in doctest.
    """
    out, inside, indent = [], False, ""
    for line in text.splitlines():
        stripped = line.lstrip()
        if not inside and stripped.startswith(">>>"):
            indent = line[:len(line) - len(stripped)]
            out.append(f"{indent}```pycon")
            inside = True
        elif inside and not stripped:
            out.append(f"{indent}```")
            inside = False
        out.append(line)
    if inside:
        out.append(f"{indent}```")
    return "\n".join(out)


class DoctestFences(griffe.Extension):
    def on_object(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None and ">>>" in obj.docstring.value:
            obj.docstring.value = fence_examples(obj.docstring.value)
