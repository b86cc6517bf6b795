"""A small reference velocity field with a hand-written VJP (spec chapter F, 03-inference.md).

It lets the samplers and the guided baseline run without any deep-learning
framework, and its weights travel inside the conformance vectors. The field
mixes all tokens (so the guidance VJP has cross-token structure) and takes a
per-token flow time:

    phi(t)_j = [t_j, sin(pi t_j), cos(pi t_j)]                 # [H, 3]
    h = tanh(vec(x) W1 + vec(phi(t)) Wt + obs Wo + b1)         # [K]
    v = reshape(h W2 + b2, [H, A])

Every vector-matrix product is summed in index order (:func:`vecmat`, [F-4]).
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_int, check_real

PARAM_NAMES = ("W1", "Wt", "Wo", "b1", "W2", "b2")


def vecmat(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``v @ M`` for v [n], M [n, K], summed over i in index order ([F-4]).

    One rounding per product and one per addition, ``((v0 M0 + v1 M1) + v2 M2) + ...``,
    so the result does not depend on which BLAS kernel the CPU selects
    (OpenBLAS accumulates in kernel-specific orders) and the vectors built
    from this field regenerate to the same bytes ([CF-3]).

    >>> vecmat(np.array([1.0, 2.0]), np.array([[1.0, 0.5], [3.0, -1.0]]))
    array([ 7. , -1.5])
    """
    v = check_array("v", v, ndim=1)
    M = check_array("M", M, shape=(v.shape[0], None))
    return _vecmat(v, M)


def _vecmat(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    # vecmat without the checks, for arrays the field has already validated.
    acc = v[0] * M[0]
    for i in range(1, v.shape[0]):
        acc = acc + v[i] * M[i]
    return acc


def time_features(t) -> np.ndarray:
    """phi(t): [H] -> [H, 3] ([F-1]); t flow times in [0, 1]."""
    t = check_array("t", t, ndim=1, lo=0.0, hi=1.0)
    return np.stack([t, np.sin(np.pi * t), np.cos(np.pi * t)], axis=-1)


class ReferenceVelocityField:
    """v(obs, x, t) of [F-1] with its vector-Jacobian product in x ([F-2])."""

    def __init__(self, params: dict):
        if not isinstance(params, dict):
            raise ValueError(f"params must be a dict with keys {PARAM_NAMES}, got {type(params).__name__}")
        missing = [k for k in PARAM_NAMES if k not in params]
        if missing:
            raise ValueError(f"params is missing {missing}; expected keys {PARAM_NAMES}")
        extra = sorted(str(k) for k in params if k not in PARAM_NAMES)
        if extra:  # a misspelt or foreign weight would otherwise be ignored
            raise ValueError(f"params has unknown keys {extra}; expected keys {PARAM_NAMES}")
        W1 = check_array("params['W1']", params["W1"], ndim=2)
        HA, K = W1.shape
        Wt = check_array("params['Wt']", params["Wt"], ndim=2)
        if Wt.shape[1] != K or Wt.shape[0] % 3:
            raise ValueError(f"params['Wt'] must have shape [3*H, {K}], got {list(Wt.shape)}")
        H = Wt.shape[0] // 3
        if HA % H:
            raise ValueError(f"params['W1'] must have shape [H*A, K] with H={H}, got {list(W1.shape)}")
        Wo = check_array("params['Wo']", params["Wo"], ndim=2)
        if Wo.shape[1] != K:
            raise ValueError(f"params['Wo'] must have shape [obs_dim, {K}], got {list(Wo.shape)}")
        self.params = {
            "W1": W1, "Wt": Wt, "Wo": Wo,
            "b1": check_array("params['b1']", params["b1"], shape=(K,)),
            "W2": check_array("params['W2']", params["W2"], shape=(K, HA)),
            "b2": check_array("params['b2']", params["b2"], shape=(HA,)),
        }
        self.horizon, self.action_dim, self.obs_dim, self.hidden = H, HA // H, Wo.shape[0], K

    @classmethod
    def init(cls, seed: int, horizon: int, action_dim: int, obs_dim: int, hidden: int = 32,
             scale: float = 1.0) -> "ReferenceVelocityField":
        """Random field from ``seed`` (numpy default_rng), fan-in scaled normal weights ([F-3])."""
        seed = check_int("seed", seed, 0)
        H = check_int("horizon", horizon, 1, 4096)
        A = check_int("action_dim", action_dim, 1, 4096)
        O = check_int("obs_dim", obs_dim, 1, 1 << 20)
        K = check_int("hidden", hidden, 1, 4096)
        scale = check_real("scale", scale, 0.0, lo_open=True)
        rng = np.random.default_rng(seed)
        n = lambda *shape: rng.standard_normal(shape)
        params = {
            "W1": n(H * A, K) * scale / np.sqrt(H * A),
            "Wt": n(3 * H, K) * scale / np.sqrt(3 * H),
            "Wo": n(O, K) * scale / np.sqrt(O),
            "b1": n(K) * 0.1,
            "W2": n(K, H * A) * scale / np.sqrt(K),
            "b2": n(H * A) * 0.1,
        }
        return cls(params)

    def _check(self, obs, x, t):
        obs = check_array("obs", obs, shape=(self.obs_dim,))
        x = check_array("x", x, shape=(self.horizon, self.action_dim))
        t = check_array("t", t, shape=(self.horizon,), lo=0.0, hi=1.0)
        return obs, x, t

    def _hidden(self, obs, x, t) -> np.ndarray:
        p = self.params
        pre = (_vecmat(x.reshape(-1), p["W1"]) + _vecmat(time_features(t).reshape(-1), p["Wt"])
               + _vecmat(obs, p["Wo"]) + p["b1"])
        return np.tanh(pre)

    def __call__(self, obs, x, t) -> np.ndarray:
        """Velocity [H, A] at chunk x [H, A] with per-token time t [H] ([F-1])."""
        obs, x, t = self._check(obs, x, t)
        h = self._hidden(obs, x, t)
        return (_vecmat(h, self.params["W2"]) + self.params["b2"]).reshape(self.horizon, self.action_dim)

    def vjp(self, obs, x, t, cotangent) -> np.ndarray:
        """(d v / d x)^T cotangent, shape [H, A] ([F-2])."""
        obs, x, t = self._check(obs, x, t)
        g = check_array("cotangent", cotangent, shape=(self.horizon, self.action_dim))
        h = self._hidden(obs, x, t)
        dh = _vecmat(g.reshape(-1), self.params["W2"].T) * (1.0 - h * h)
        return _vecmat(dh, self.params["W1"].T).reshape(self.horizon, self.action_dim)

    def to_dict(self) -> dict:
        return {k: v.tolist() for k, v in self.params.items()}
