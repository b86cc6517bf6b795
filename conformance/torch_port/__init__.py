"""A standalone PyTorch port of the softrtc rules, written as a porting example ([CF-21], spec/40-conformance.md).

Modules: checks (input validation), weights (E, W, G-1), training (C, L),
field (the reference velocity field F), sampling (S, G in the spec's time
convention), flipped (the same samplers in the flipped convention of [V-1]).
adapter.py and adapter_flipped.py plug the port into `softrtc conformance run`.
Nothing here imports softrtc.reference: the port is checked only through the vectors.
"""
