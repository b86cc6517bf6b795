"""JAX implementation of softrtc; module names mirror softrtc.reference (see spec/00-overview.md)."""
