"""NumPy reference of the softrtc specification (spec/).

One module per chapter; every function cites the requirement ids it
implements. Importing this package needs only NumPy.
"""

from . import (conventions, corruption, delays, endpoints, executor, guidance, loss, methods, metrics,
               sampler, velocity, weights)
from .endpoints import EndpointRule, delay_scaled, endpoint, fixed, hard, offset
from .weights import SoftWindow, hard_weights, prefix_weights, soft_weights

__all__ = [
    "conventions", "corruption", "delays", "endpoints", "executor", "guidance", "loss", "methods", "metrics",
    "sampler", "velocity", "weights", "EndpointRule", "delay_scaled", "endpoint", "fixed", "hard",
    "offset", "SoftWindow", "hard_weights", "prefix_weights", "soft_weights",
]
