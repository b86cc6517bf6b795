"""softrtc: reference semantics of real-time chunking (RTC) and Soft RTC.

Subpackages:
  softrtc.reference   NumPy reference of every rule in spec/ (needs only NumPy)
  softrtc.jax         fast JAX twin of the reference, module for module
  softrtc.conformance vector generator and runner for any implementation
  softrtc.arm         pymunk arm sorting task and real-time runtime
  softrtc.kinetix     Kinetix benchmark levels and evaluation protocol

Importing ``softrtc`` itself imports nothing beyond the standard library.
"""

__version__ = "0.1.0"
