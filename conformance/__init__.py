"""Conformance suite of the softrtc specification (chapter CF, spec/40-conformance.md).

  generate        writes the JSON vector files of conformance/vectors/ from the NumPy reference ([CF-1]..[CF-6]);
                  the cases themselves in cases_training, cases_runtime (cases_base: tolerances, exact entries)
  adapter         the adapter interface and loader for implementations under test ([CF-7]..[CF-12], [CF-27])
  vectors_io      reading vector files, the number convention and integrity ([CF-23], [CF-25]);
  vector_checks   the checks of each case before any implementation runs ([CF-24], [CF-28])
  runner          runs every case ([CF-13]..[CF-18]); compare: the comparison and the time conventions
                  ([CF-5], [CF-10]); results: summary, JSON report, JUnit, output paths ([CF-15], [CF-39])
  protocol        the runner's end of the child-process protocol ([CF-29]..[CF-31]); host: the Python end;
  invoke          one call of a Python adapter, shared by the host and --in-process
  cli             `softrtc conformance run|generate` ([CF-19])
  ports/js        a JavaScript port speaking the protocol (not a Python package)

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
