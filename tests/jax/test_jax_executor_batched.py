"""The JAX executor's segment with one delay per environment and its host-side sources ([X-4], [X-8])."""

import jax
import numpy as np
import pytest

from softrtc.jax import executor as JX


def test_segment_takes_one_delay_per_environment():
    """X-4, X-8: with delays [n], env e executes prev[s .. s + d_e - 1] then new[d_e .. s - 1]."""
    H, s, A = 6, 3, 1
    prev = np.arange(3 * H, dtype=np.float32).reshape(3, H, A)  # env e: 6e .. 6e + 5
    new = -1.0 - prev
    got = np.asarray(JX.segment(prev, new, s, np.array([0, 1, 3])))[..., 0]
    # By hand: env 0 takes new[0..2]; env 1 prev[3], new[1..2]; env 2 prev[3..5].
    np.testing.assert_array_equal(got, [[-1.0, -2.0, -3.0], [9.0, -8.0, -9.0], [15.0, 16.0, 17.0]])
    # Traced per-env delays give the same segments as one call per env with a scalar delay.
    traced = jax.jit(lambda p, n, d: JX.segment(p, n, s, d))(prev, new, np.array([0, 1, 3], np.int32))
    for e, d in enumerate((0, 1, 3)):
        np.testing.assert_array_equal(np.asarray(traced[e]), np.asarray(JX.segment(prev[e], new[e], s, d)))


def test_segment_checks_per_environment_delays():
    """X-1, X-8, N-7: per-env delays need the batch shape and [X-1]'s range."""
    prev = np.zeros((2, 8, 1))
    with pytest.raises(ValueError, match=r"^d entries must be integers in \[0, 4\]"):
        JX.segment(prev, prev, 4, np.array([0, 5]))
    with pytest.raises(ValueError, match=r"^d must have shape \[2\]"):
        JX.segment(prev, prev, 4, np.array([0, 1, 2]))


def test_segment_sources_name_each_step():
    """X-4, X-8: step i comes from the previous chunk's token s + i when i < d, else the new chunk's token i."""
    from_prev, token = JX.segment_sources(8, 4, 2)
    assert from_prev.tolist() == [True, True, False, False] and token.tolist() == [4, 5, 2, 3]
    from_prev, token = JX.segment_sources(8, 4, 0)
    assert not from_prev.any() and token.tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 4\], got 5"):
        JX.segment_sources(8, 4, 5)
    with pytest.raises(ValueError, match=r"^s must be an integer in \[1, 8\]"):
        JX.segment_sources(8, 9, 0)
