"""A standalone PyTorch port of the softrtc rules, written as a porting example ([CF-21], spec/40-conformance.md).

Modules: checks (input validation), weights (E, W, G-1, S-6), delays (D),
training (C, L), field (the reference velocity field and its VJP, F), sampling
(S, G in the spec's time convention), executor (X), metrics (M), flipped (the
time-dependent rules in the flipped convention of [V-1]).
adapter.py and adapter_flipped.py plug the port into `softrtc conformance run`.
Nothing here imports softrtc.reference: the port is checked only through the vectors.
"""
