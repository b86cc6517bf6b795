"""Conformance suite of the softrtc specification (chapter CF, spec/40-conformance.md).

  generate   writes the JSON vector files of conformance/vectors/ from the NumPy reference ([CF-1]..[CF-6])
  adapter    the adapter interface and loader for implementations under test ([CF-7]..[CF-12])
  runner     runs every vector case against an adapter and reports per requirement id ([CF-13]..[CF-18])
  cli        `softrtc conformance run|generate` ([CF-19])

Importing this package imports only the standard library and NumPy.
"""

from pathlib import Path

from .._files import package_data_dir

FORMAT_VERSION = "1.2"
SPEC_VERSION = "0.1.0"


def vectors_dir() -> Path:
    """The shipped vector directory ([CF-1]): package data of ``softrtc.conformance``, found through
    ``importlib.resources`` so that an installed wheel finds it wherever it lies."""
    return package_data_dir(__name__, "vectors")


__all__ = ["FORMAT_VERSION", "SPEC_VERSION", "vectors_dir"]
