"""Fixtures shared by the Kinetix tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def restore_cache():
    """The process-wide compile cache of [KC-1] as it was before the test: tests that configure it leave no trace."""
    from softrtc.kinetix import cache  # imported here: collecting the tests must not need JAX

    before = dict(cache._state)
    yield
    cache.clear_memory()
    if before["configured"]:
        cache.enable_compile_cache(before["dir"])
    else:
        cache.enable_compile_cache(None)
        cache._state["configured"] = False
