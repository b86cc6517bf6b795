"""The reference velocity field of [F-1] in JAX; twin of ``softrtc.reference.velocity``.

Same parameters dict (W1, Wt, Wo, b1, W2, b2) as the NumPy field, cast to
float32. The field is a pytree, so it can be passed to jitted functions as an
argument. It acts on a single example (obs [O], x [H, A], t [H]) or on a
batch (obs [B, O], x [B, H, A], t [B, H]); a batch is what the samplers use.

It also offers the fast-path interface of the flow policy:
``time_conditioning(t)`` computes the time-dependent part of the hidden
pre-activation, ``vec(phi(t)) Wt``, and ``apply_conditioned(obs, x, cond)``
evaluates the field from it, so ``apply_conditioned(obs, x,
time_conditioning(t)) == field(obs, x, t)`` up to float rounding.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp

from softrtc.reference import velocity as _ref

from . import _validate as v

PARAM_NAMES = _ref.PARAM_NAMES


def time_features(t) -> jax.Array:
    """phi(t): [..., H] -> [..., H, 3] ([F-1]); t flow times in [0, 1] (checked when concrete)."""
    t = v.array("t", t, lo=0.0, hi=1.0)
    return jnp.stack([t, jnp.sin(jnp.pi * t), jnp.cos(jnp.pi * t)], axis=-1)


@jax.tree_util.register_pytree_node_class
class ReferenceVelocityField:
    """v(obs, x, t) of [F-1] with a hand-written VJP ([F-2]), in float32."""

    def __init__(self, params: dict):
        """Checks the parameters as the reference does ([F-1], [N-7]): exactly the six arrays of [F-1],
        real, finite (when concrete), no empty axis, consistent shapes. Traced parameters (a field
        built inside ``jit``) are checked for shape and dtype only."""
        if isinstance(params, _ref.ReferenceVelocityField):
            params = params.params
        if not isinstance(params, Mapping):
            raise ValueError(f"params must be a dict with keys {PARAM_NAMES}, got {type(params).__name__}")
        missing = [k for k in PARAM_NAMES if k not in params]
        if missing:
            raise ValueError(f"params is missing {missing}; expected keys {PARAM_NAMES}")
        extra = [k for k in params if k not in PARAM_NAMES]
        if extra:
            raise ValueError(f"params has unknown keys {extra}; expected exactly the keys {PARAM_NAMES}")
        W1 = v.array("params['W1']", params["W1"], ndim=2)
        HA, K = W1.shape
        Wt = v.array("params['Wt']", params["Wt"], ndim=2)
        if Wt.shape[1] != K or Wt.shape[0] % 3:
            raise ValueError(f"params['Wt'] must have shape [3*H, {K}], got {list(Wt.shape)}")
        H = Wt.shape[0] // 3
        if HA % H:
            raise ValueError(f"params['W1'] must have shape [H*A, K] with H={H}, got {list(W1.shape)}")
        Wo = v.array("params['Wo']", params["Wo"], ndim=2)
        if Wo.shape[1] != K:
            raise ValueError(f"params['Wo'] must have shape [obs_dim, {K}], got {list(Wo.shape)}")
        self.params = {
            "W1": W1, "Wt": Wt, "Wo": Wo,
            "b1": v.array("params['b1']", params["b1"], shape=(K,)),
            "W2": v.array("params['W2']", params["W2"], shape=(K, HA)),
            "b2": v.array("params['b2']", params["b2"], shape=(HA,)),
        }
        self.horizon, self.action_dim, self.obs_dim, self.hidden = H, HA // H, Wo.shape[0], K

    @classmethod
    def from_reference(cls, field: _ref.ReferenceVelocityField) -> "ReferenceVelocityField":
        """The JAX twin of a NumPy reference field (same weights) ([F-3])."""
        if not isinstance(field, _ref.ReferenceVelocityField):
            raise ValueError(f"field must be a reference ReferenceVelocityField, got {type(field).__name__}")
        return cls(field.params)

    # Pytree protocol: parameters are leaves, so jit sees them as arguments, not constants.
    def tree_flatten(self):
        return tuple(self.params[k] for k in PARAM_NAMES), None

    @classmethod
    def tree_unflatten(cls, aux, leaves):
        obj = object.__new__(cls)
        obj.params = dict(zip(PARAM_NAMES, leaves))
        HA, K = obj.params["W1"].shape
        H = obj.params["Wt"].shape[0] // 3
        obj.horizon, obj.action_dim, obj.obs_dim, obj.hidden = H, HA // H, obj.params["Wo"].shape[0], K
        return obj

    def _check(self, obs, x):
        H, A, O = self.horizon, self.action_dim, self.obs_dim
        x = v.array("x", x)
        if x.ndim not in (2, 3) or x.shape[-2:] != (H, A):
            raise ValueError(f"x must have shape [H, A] = [{H}, {A}] or [B, {H}, {A}], got {list(x.shape)}")
        obs = v.array("obs", obs, shape=x.shape[:-2] + (O,))
        return obs, x

    def time_conditioning(self, t) -> jax.Array:
        """Time part of the hidden pre-activation, vec(phi(t)) Wt: [..., H] or [..., 1] -> [..., K].

        A last dim of 1 means one time shared by all tokens.
        """
        t = v.array("t", t, lo=0.0, hi=1.0)
        if t.ndim < 1 or t.shape[-1] not in (1, self.horizon):
            raise ValueError(f"t must have shape [..., {self.horizon}] or [..., 1], got {list(t.shape)}")
        t = jnp.broadcast_to(t, t.shape[:-1] + (self.horizon,))
        phi = time_features(t).reshape(t.shape[:-1] + (3 * self.horizon,))
        return phi @ self.params["Wt"]

    def _hidden(self, obs, x, cond):
        p = self.params
        pre = x.reshape(x.shape[:-2] + (-1,)) @ p["W1"] + cond + obs @ p["Wo"] + p["b1"]
        return jnp.tanh(pre)

    def _check_cond(self, cond, x) -> jax.Array:
        """``cond`` of :meth:`apply_conditioned`: real, [K] or [b, K] with b in {1, B} ([N-7]).

        Shape and dtype are checked always, finiteness when concrete; any other
        shape would broadcast into the hidden layer silently.
        """
        K = self.hidden
        batch = x.shape[:-2]
        if cond is None:
            raise ValueError(f"cond must be an array [{K}] or [b, {K}] (time_conditioning of this field), got None")
        c = v.array("cond", cond)
        if not (c.shape == (K,) or (c.ndim == 2 and c.shape[1] == K and c.shape[0] in (1,) + batch)):
            b = f"b in {{1, B={batch[0]}}}" if batch else "b = 1"
            raise ValueError(f"cond must have shape [K={K}] or [b, {K}] with {b} (time_conditioning of this "
                             f"field), got {list(c.shape)}")
        return c

    def apply_conditioned(self, obs, x, cond) -> jax.Array:
        """Velocity from a precomputed ``cond = time_conditioning(t)``; cond [K] or [b, K], b in {1, B}."""
        obs, x = self._check(obs, x)
        h = self._hidden(obs, x, self._check_cond(cond, x))
        return (h @ self.params["W2"] + self.params["b2"]).reshape(x.shape)

    def apply_conditioned_split(self, obs, x, cond, head: int) -> tuple:
        """``apply_conditioned`` as ``(v[..., :head, :], v[..., head:, :])`` ([G-7], the interface of [P-18]).

        The output layer is evaluated on the columns of each token group only,
        so a VJP of the first group skips the second group's output columns.
        ``head`` is a static integer in [1, H - 1].
        """
        head = v.check_int("head", head, 1, self.horizon - 1)
        obs, x = self._check(obs, x)
        h = self._hidden(obs, x, self._check_cond(cond, x))
        W2, b2, n = self.params["W2"], self.params["b2"], head * self.action_dim
        lead = x.shape[:-2]
        return ((h @ W2[:, :n] + b2[:n]).reshape(lead + (head, self.action_dim)),
                (h @ W2[:, n:] + b2[n:]).reshape(lead + (self.horizon - head, self.action_dim)))

    def __call__(self, obs, x, t) -> jax.Array:
        """Velocity [..., H, A] at x [..., H, A] with per-token time t [..., H] ([F-1])."""
        obs, x = self._check(obs, x)
        t = v.array("t", t, shape=x.shape[:-1], lo=0.0, hi=1.0)
        return _velocity(self, obs, x, t)

    def vjp(self, obs, x, t, cotangent) -> jax.Array:
        """Hand-written (dv/dx)^T cotangent, shape of x ([F-2])."""
        obs, x = self._check(obs, x)
        t = v.array("t", t, shape=x.shape[:-1], lo=0.0, hi=1.0)
        g = v.array("cotangent", cotangent, shape=x.shape)
        return _vjp(self, obs, x, t, g)


# Checked by the methods above; jitted so an eager call is one dispatch, not one per op.
@jax.jit
def _velocity(field, obs, x, t):
    return field.apply_conditioned(obs, x, field.time_conditioning(t))


@jax.jit
def _vjp(field, obs, x, t, g):
    h = field._hidden(obs, x, field.time_conditioning(t))
    dh = (g.reshape(g.shape[:-2] + (-1,)) @ field.params["W2"].T) * (1.0 - h * h)
    return (dh @ field.params["W1"].T).reshape(x.shape)
