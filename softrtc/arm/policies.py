"""Arm policies: a flow policy with its normalizer and chunk generator ([A-19], [S-6]).

Chunks leave the policy in physical units and inside the action ranges of
[A-8] ([A-19]); inference is :class:`softrtc.jax.fast_chunks.FastChunks` ([S-6]). Training is
in :mod:`softrtc.arm.training`, checkpoint files in
:mod:`softrtc.arm.checkpoints`, the policy input in :mod:`softrtc.arm.features`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.jax import methods as jmethods
from softrtc.jax.fast_chunks import FastChunks
from softrtc.jax.policy import FlowPolicy
from softrtc.jax.weights import SoftWindow
from softrtc.reference._validate import check_choice, check_int
from softrtc.reference.methods import check_method_step

from .env import ACTION_DIM, OBS_DIM, ArmConfig
from .features import FEATURE_DIM, Normalizer, _real_array, action_bounds, policy_features
from .policy_config import ArmPolicyConfig, new_model

__all__ = ["ArmPolicy", "untrained_policy"]


def _check_window(window) -> None:
    """``window`` is None or a JAX :class:`softrtc.jax.weights.SoftWindow` ([W-7]), checked before any compilation."""
    if window is not None and not isinstance(window, SoftWindow):
        raise ValueError(f"window must be a softrtc.jax.weights.SoftWindow or None (convert a reference window with "
                         f"softrtc.jax.weights.from_reference), got {type(window).__name__}")


def check_parts(model, normalizer, config) -> None:
    """The parts of one arm policy: a ``FlowPolicy`` of ``config``'s architecture, a ``Normalizer`` and an
    ``ArmPolicyConfig`` ([A-17], [A-18])."""
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    if not isinstance(normalizer, Normalizer):
        raise ValueError(f"normalizer must be a Normalizer, got {type(normalizer).__name__}")
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    if model.config != config.policy_config() or model.obs_dim != FEATURE_DIM or model.action_dim != ACTION_DIM:
        raise ValueError("model must have the architecture of config (ArmPolicyConfig.policy_config)")


class ArmPolicy:
    """A flow policy with its normalizer and chunk generator ([A-19], [S-6]).

    ``generate(obs, prior, d, key)`` returns a chunk ``[H, 4]`` in physical units.
    ``prior`` (``[H, 4]``, physical, [X-3]) is ``None`` for the first chunk,
    which every method generates with the naive sampler and ``d = 0`` ([X-2]).
    The network's output is mapped back to physical units and clipped to the
    action ranges of [A-8] ([A-19]); the clipped chunk is what is executed and
    what later priors are built from. ``step`` is the training-time sampler's
    solver step ([S-10]), default "algorithm1"; the guided methods take only
    that one ([S-14]).
    """

    def __init__(self, model: FlowPolicy, normalizer: Normalizer, config: ArmPolicyConfig, method: str,
                 trained_as: str | None = None, meta: dict | None = None, env_config: ArmConfig | None = None,
                 window: SoftWindow | None = None, step: str = "algorithm1"):
        check_parts(model, normalizer, config)
        self.method = check_choice("method", method, jmethods.METHODS)
        self.step = check_method_step(self.method, step)
        _check_window(window)
        if trained_as is not None and not isinstance(trained_as, str):
            raise ValueError(f"trained_as must be a str or None, got {trained_as!r}")
        if meta is not None and not isinstance(meta, dict):
            raise ValueError(f"meta must be a dict or None, got {type(meta).__name__}")
        self.trained_as = trained_as or method
        self.meta = dict(meta or {})
        self.model, self.normalizer, self.config = model, normalizer, config
        self.train_config = None
        self.H, self.s, self.T = config.horizon, config.execute_horizon, config.num_steps
        self.low, self.high = action_bounds(env_config)
        # train_soft's window ([W-7]); default the paper's main setting.
        self.window = SoftWindow() if window is None else window
        # float32 statistics: the network's inputs and outputs are float32.
        self._nm = tuple(np.asarray(a, np.float32) for a in (normalizer.obs_mean, normalizer.obs_std,
                                                            normalizer.act_mean, normalizer.act_std))
        self._fast = None

    @property
    def chunks(self) -> FastChunks:
        """The policy's :class:`~softrtc.jax.fast_chunks.FastChunks` ([S-6]), built on first use (the tables of
        every delay depend on the parameters and the window only)."""
        if self._fast is None:
            # Only train_soft has a window ([W-7]); a window given to another method is checked against H ([S-8]).
            window = self.window if self.method == "train_soft" else None
            self._fast = FastChunks(self.model, self.method, self.s, self.T, window, step=self.step)
        return self._fast

    def _obs(self, obs) -> np.ndarray:
        """The normalized policy input ``[1, FEATURE_DIM]`` of one observation ([A-17], [A-18])."""
        o = _real_array("obs", obs)
        if o.shape != (OBS_DIM,) or not np.all(np.isfinite(o)):
            raise ValueError(f"obs must be a finite vector of shape [{OBS_DIM}], got shape {list(o.shape)}")
        return ((policy_features(o).astype(np.float32) - self._nm[0]) / self._nm[1])[None]

    def generate(self, obs, prior, d, key) -> np.ndarray:
        """One chunk ``[H, 4]`` (float64, physical units, within [A-8]) for delay ``d`` ([S-6], [A-19])."""
        o = self._obs(obs)
        if not isinstance(key, jax.Array) or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed))")
        if key.shape != ():
            raise ValueError(f"key must be a single typed JAX PRNG key of shape (), got shape {tuple(key.shape)}")
        if prior is None:
            check_int("d", d, 0, 0)
            z = self.chunks.first(o, key)
        else:
            d = check_int("d", d, 0, self.config.max_delay)
            p = _real_array("prior", prior)
            if p.shape != (self.H, ACTION_DIM) or not np.all(np.isfinite(p)):
                raise ValueError(f"prior must be a finite array of shape [{self.H}, {ACTION_DIM}], got {list(p.shape)}")
            y = (p.astype(np.float32) - self._nm[2]) / self._nm[3]
            z = self.chunks.next(o, y[None], d, key)
        z = np.asarray(z)[0] * self._nm[3] + self._nm[2]
        return np.clip(z.astype(np.float64), self.low, self.high)

    def warmup(self) -> None:
        """Compile both generators once (so the first timed call is not a compilation)."""
        obs = np.zeros(OBS_DIM)
        c = self.generate(obs, None, 0, jax.random.key(0))
        self.generate(obs, c, min(1, self.config.max_delay), jax.random.key(1))


def untrained_policy(seed: int = 0, method: str = "naive", config: ArmPolicyConfig = ArmPolicyConfig(),
                     window: SoftWindow | None = None) -> ArmPolicy:
    """A randomly initialised policy with identity normalization, for fast conformance tests.

    adaLN-zero makes the mixer blocks identity at initialisation, so the output
    is an affine function of the inputs; the normalizer maps it onto the action
    centre of the joint ranges so rollouts stay valid.
    """
    seed = check_int("seed", seed, 0, 2**31 - 1)
    method = check_choice("method", method, jmethods.METHODS)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    _check_window(window)
    model = new_model(config, seed)
    norm = Normalizer(np.zeros(FEATURE_DIM), np.ones(FEATURE_DIM), np.array([0.0, -1.0, 0.0, 0.5]),
                      np.array([0.3, 0.3, 0.3, 0.3]))
    return ArmPolicy(model, norm, config, method, trained_as="untrained", window=window)
