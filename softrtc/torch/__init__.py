"""Soft RTC for PyTorch policies ([PT-1]): batched, device- and dtype-preserving, differentiable.

Modules, named as in ``softrtc.reference`` and ``softrtc.jax``: ``endpoints``,
``weights`` (E, W), ``delays`` (D), ``corruption`` (C), ``loss`` (L),
``velocity`` (the reference field, F), ``sampler`` (S, with precomputed
conditioning), ``guidance`` (G), ``executor`` (X), ``metrics`` (M), ``methods``
([S-6]), ``conventions`` ([V-1]); ``training`` (the objective a training step
calls), ``policy`` (a small flow policy), ``bench`` (``softrtc bench torch``),
``arm`` (``softrtc arm torch``, with the arm extra) and ``cli``. Importing the
package imports nothing; its modules import torch (``arm`` also the arm package).
"""
