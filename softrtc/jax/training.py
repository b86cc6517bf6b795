"""Behaviour cloning with training-time RTC in JAX (spec chapter T, ``spec/31-training-jax.md``).

One train step draws, per example, a delay ``d`` ([D-1]..[D-4]), a flow time
``tau ~ U[0, 1)`` ([C-1]) and noise ``eps``; builds the method's token weights
(``none``: w = 0, ``hard``: [W-8], ``soft``: [W-7]); corrupts the chunk
([C-2]); evaluates the policy at the per-token times; and minimises the
weighted loss of [L-2] averaged over the batch ([L-3]) with clipped AdamW
([T-6]). The delay is sampled inside the jitted step, so one compilation
serves every delay ([T-7]).

>>> import flax.nnx as nnx, jax, jax.numpy as jnp
>>> from softrtc.jax.policy import FlowPolicy, PolicyConfig
>>> pol = FlowPolicy(obs_dim=3, action_dim=2, rngs=nnx.Rngs(0),
...                  config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4,
...                                      num_layers=1, action_chunk_size=8))
>>> step = make_train_step(pol, TrainConfig(method="soft", batch_size=4))
>>> state = step.init_state()
>>> state, metrics = step(state, (jnp.zeros((4, 3)), jnp.zeros((4, 8, 2))), jax.random.key(0))
>>> int(state.step), sorted(metrics)
(1, ['delay_mean', 'grad_norm', 'learning_rate', 'loss'])
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import Any, Iterable, Iterator, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from softrtc.reference._validate import check_int

from . import weights as _jw
from .corruption import corrupt
from .delays import delay_cdf, delay_probs
from .loss import ETA, flow_matching_loss
from .policy import FlowPolicy
from .train_config import MAX_BATCH, MAX_STEPS, METHODS, TrainConfig, _optimizer, _optimizer_key, make_optimizer

__all__ = [
    "METHODS",
    "TrainConfig",
    "TrainState",
    "TrainStep",
    "make_train_step",
    "make_optimizer",
    "train",
]


# --------------------------------------------------------------------------- state and step


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """Everything a step updates ([T-7]): policy parameters (``nnx.State``), optimiser state, step count."""

    params: Any
    opt_state: Any
    step: jax.Array


def _check_key(key: Any) -> jax.Array:
    """A PRNG key: typed (``jax.random.key``) scalar or raw uint32 ``[2]`` (``jax.random.PRNGKey``) [N-9]."""
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.ndim != 0:
            raise ValueError(f"key must be a single PRNG key, got a key array of shape {key.shape}")
        return key
    if isinstance(key, (jax.Array, np.ndarray)) and key.dtype == np.uint32 and key.shape == (2,):
        return jnp.asarray(key)
    raise ValueError(f"key must be a PRNG key (jax.random.key(seed) or jax.random.PRNGKey(seed)), got {key!r}")


def _float_batch(name: str, value: Any, shape: tuple, check_finite: bool) -> jax.Array:
    if isinstance(value, (bool, np.bool_)) or getattr(value, "dtype", None) == np.bool_:
        raise ValueError(f"{name} must be a real array, got a boolean")
    try:
        arr = value if isinstance(value, jax.Array) else np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real array, got {type(value).__name__}") from exc
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) \
            or np.issubdtype(arr.dtype, np.bool_):
        raise ValueError(f"{name} must have a real dtype, got {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "[" + ", ".join("B" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(arr.shape)}")
    if check_finite and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name} must contain only finite values (no NaN or inf)")
    with np.errstate(over="ignore"):
        out = jnp.asarray(arr, jnp.float32)
    if check_finite and not np.all(np.isfinite(np.asarray(out))):  # finite in float64, beyond float32
        raise ValueError(f"{name} must lie within float32 range (|x| < 3.4e38)")
    return out


def _unpack_batch(batch: Any) -> tuple[Any, Any]:
    if isinstance(batch, Mapping):
        if "obs" not in batch or "actions" not in batch:
            raise ValueError(f"batch must have keys 'obs' and 'actions', got {sorted(map(str, batch))}")
        return batch["obs"], batch["actions"]
    if isinstance(batch, (tuple, list)) and len(batch) == 2:
        return batch[0], batch[1]
    raise ValueError("batch must be (obs [B, O], actions [B, H, A]) or a mapping with keys 'obs', 'actions'")


@dataclasses.dataclass(frozen=True)
class _StepSpec:
    """Static (hashable) part of a step: the compiled code is shared by every step with an equal spec.

    Only what changes the program is static: the architecture, the time path
    (``scalar_time`` for ``none``) and the optimiser. Method weights, the delay
    CDF and ``d_min`` are traced tables, so hard and soft steps and every window
    and delay distribution share one compilation ([T-7]).
    """

    graphdef: Any
    horizon: int
    action_dim: int
    scalar_time: bool
    optimizer: tuple


def _sample(spec: _StepSpec, tables: tuple, key: jax.Array, batch_size: int) -> dict[str, jax.Array]:
    """Per-example draws of one step ([T-2], [D-3], [C-1], [T-3])."""
    weight_table, cdf, d_min = tables
    # The split is the same for every method, so `none` and `hard`/`soft` with d = 0
    # see the same tau and eps for the same key ([T-5]).
    k_d, k_tau, k_eps = jax.random.split(key, 3)
    # [D-3] inverse CDF d = d_min + #{k : cdf_k <= u}. The CDF is built on the host; the traced
    # table cannot go through delays.sample_delay, whose sum check needs a concrete table.
    u = jax.random.uniform(k_d, (batch_size,), jnp.float32)
    d = d_min + jnp.sum(cdf <= u[:, None], axis=-1).astype(jnp.int32)
    tau = jax.random.uniform(k_tau, (batch_size,), jnp.float32)
    eps = jax.random.normal(k_eps, (batch_size, spec.horizon, spec.action_dim), jnp.float32)
    return {"delay": d, "tau": tau, "noise": eps, "weights": weight_table[d]}


def _loss_fn(spec: _StepSpec, tables: tuple, params: Any, rest: Any, obs: jax.Array, actions: jax.Array,
             key: jax.Array):
    model = nnx.merge(spec.graphdef, params, rest)
    draw = _sample(spec, tables, key, obs.shape[0])
    w, tau, eps = draw["weights"], draw["tau"], draw["noise"]
    x, tj = corrupt(actions, eps, w, tau)  # [C-1], [C-2]
    # `none` is plain flow matching: one time per sample ([B]), so the policy computes its
    # time conditioning once per sample and shares it over the tokens ([P-9]).
    pred = model(obs, x, tau if spec.scalar_time else tj)
    loss = jnp.mean(flow_matching_loss(pred, actions, eps, w, ETA))  # [L-1]..[L-3]
    return loss, jnp.mean(draw["delay"].astype(jnp.float32))


@functools.partial(jax.jit, static_argnums=0)
def _update(spec: _StepSpec, tables: tuple, rest: Any, state: "TrainState", obs: jax.Array,
            actions: jax.Array, key: jax.Array):
    optimizer, schedule = _optimizer(spec.optimizer)
    grad_fn = jax.value_and_grad(_loss_fn, argnums=2, has_aux=True)
    (loss, dmean), grads = grad_fn(spec, tables, state.params, rest, obs, actions, key)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads),
               "learning_rate": jnp.asarray(schedule(state.step), jnp.float32), "delay_mean": dmean}
    return TrainState(params, opt_state, state.step + 1), metrics


_draw_jit = jax.jit(_sample, static_argnums=(0, 3))
_loss_jit = jax.jit(_loss_fn, static_argnums=0)


class TrainStep:
    """A compiled behaviour-cloning step for one policy architecture and config ([T-7]).

    Build with :func:`make_train_step`. ``step(state, batch, key) -> (state, metrics)``
    validates its inputs ([T-10]) and runs the jitted update; ``metrics`` holds
    device scalars ``loss`` (batch loss before the update, [L-3]), ``grad_norm``
    (before clipping), ``learning_rate`` (used by this update) and ``delay_mean``.
    Steps built for equal architectures and equal configs share one compilation
    per batch shape.

    Attributes: ``config``, ``obs_dim``, ``action_dim``, ``horizon`` (H),
    ``weight_table`` ([H + 1, H]: weights per delay, [T-3]), ``delay_table``
    (probabilities of d_min .. d_max), ``optimizer``, ``schedule``, and
    ``jitted(state, obs, actions, key)``, the raw jitted update without host-side
    checks (for benchmarks; inputs must already be valid float32 arrays).
    """

    def __init__(self, policy: FlowPolicy, config: TrainConfig, *, check_finite: bool = True):
        if not isinstance(policy, FlowPolicy):
            raise ValueError(f"policy must be a FlowPolicy, got {type(policy).__name__}")
        if not isinstance(config, TrainConfig):
            raise ValueError(f"config must be a TrainConfig, got {type(config).__name__}")
        if not isinstance(check_finite, bool):
            raise ValueError(f"check_finite must be a bool, got {check_finite!r}")
        self.config = config
        self.check_finite = check_finite
        self.obs_dim = policy.obs_dim
        self.action_dim = policy.action_dim
        self.horizon = H = policy.action_chunk_size
        self._arch = (policy.obs_dim, policy.action_dim, policy.config)
        graphdef, params, rest = nnx.split(policy, nnx.Param, ...)
        self._rest, self._params0 = rest, params
        self._spec = _StepSpec(graphdef, H, policy.action_dim, config.method == "none", _optimizer_key(config))
        if config.method != "none" and config.d_max > H:
            # [D-4]: a delay longer than the chunk has no weights.
            raise ValueError(f"config.d_max must be an integer in [{config.d_min}, {H}] (d <= H, [D-4]), "
                             f"got {config.d_max}")
        s = config.execute_horizon
        if s is not None and s > H:
            raise ValueError(f"config.execute_horizon must be an integer in [1, {H}] (s <= H), got {s}")
        self.weight_table = _weight_table(config, H)
        self.delay_table = delay_probs(config.delay_dist, config.d_min, config.d_max, config.delay_decay)
        self._tables = _tables(config, H, self.weight_table, self.delay_table)
        self.optimizer, self.schedule = make_optimizer(config)
        self._opt_spec = None  # shapes and dtypes of optimizer.init(params), computed on first use
        self.jitted = functools.partial(_update, self._spec, self._tables, self._rest)

    # ------------------------------------------------------------------ public API

    def init_state(self, policy: FlowPolicy | None = None) -> TrainState:
        """Fresh :class:`TrainState` from ``policy`` (default: the policy the step was built from)."""
        if policy is None:
            params = self._params0
        else:
            self._check_policy(policy)
            params = nnx.state(policy, nnx.Param)
        return TrainState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    def _check_policy(self, policy: Any) -> None:
        if not isinstance(policy, FlowPolicy):
            raise ValueError(f"policy must be a FlowPolicy, got {type(policy).__name__}")
        if (policy.obs_dim, policy.action_dim, policy.config) != self._arch:
            raise ValueError("policy must have the architecture (obs_dim, action_dim, config) of this train step, "
                             f"{self._arch}")

    def _check_params(self, name: str, params: Any) -> None:
        want = jax.tree.map(lambda a: (a.shape, a.dtype), self._params0)
        try:
            got = jax.tree.map(lambda a: (a.shape, a.dtype), params)
        except Exception:  # noqa: BLE001 - a non-array leaf means the tree is not a parameter state
            got = None
        if got is None or jax.tree.structure(got) != jax.tree.structure(want) or \
                jax.tree.leaves(got) != jax.tree.leaves(want):
            raise ValueError(f"{name} must have the parameter tree, shapes and dtypes of this train step's policy")

    def _check_opt_state(self, opt_state: Any) -> None:
        """``opt_state`` must have the tree, leaf shapes and dtypes of ``optimizer.init(params)`` ([T-10]).

        The expected tree is ``jax.eval_shape`` of the initialisation (no arrays are built), computed once:
        ``state.params`` is checked against the step's own parameter tree first, so it is the same for every
        valid state.
        """
        if self._opt_spec is None:
            shapes = jax.eval_shape(self.optimizer.init, self._params0)
            self._opt_spec = (jax.tree.structure(shapes), [(a.shape, a.dtype) for a in jax.tree.leaves(shapes)])
        treedef, leaves = self._opt_spec
        try:
            got = [(jnp.shape(a), jnp.result_type(a)) for a in jax.tree.leaves(opt_state)]
        except TypeError:  # a leaf that is not an array
            got = None
        if got is None or jax.tree.structure(opt_state) != treedef or got != leaves:
            raise ValueError("state.opt_state must be the optimiser state of this train step for its parameters "
                             "(the tree, leaf shapes and dtypes of step.optimizer.init(params), as made by "
                             f"init_state), got {type(opt_state).__name__}")

    def _check_state(self, state: Any) -> None:
        if not isinstance(state, TrainState):
            raise ValueError(f"state must be a TrainState (from init_state), got {type(state).__name__}")
        self._check_params("state.params", state.params)
        self._check_opt_state(state.opt_state)
        step = state.step
        if not isinstance(step, jax.core.Tracer):
            s = np.asarray(step)
            if s.ndim != 0 or not np.issubdtype(s.dtype, np.integer) or s.dtype == np.bool_ \
                    or not 0 <= int(s) < 2**31:
                raise ValueError(f"state.step must be an integer scalar in [0, 2147483647], got {step!r}")

    def check_batch(self, batch: Any) -> tuple[jax.Array, jax.Array]:
        """Validated ``(obs [B, O], actions [B, H, A])`` as float32 ([T-10], [N-7])."""
        obs, actions = _unpack_batch(batch)
        obs = _float_batch("obs", obs, (None, self.obs_dim), self.check_finite)
        actions = _float_batch("actions", actions, (None, self.horizon, self.action_dim), self.check_finite)
        if obs.shape[0] < 1 or actions.shape[0] != obs.shape[0]:
            raise ValueError(f"obs and actions must share a batch size B >= 1, got {obs.shape[0]} and "
                             f"{actions.shape[0]}")
        return obs, actions

    def __call__(self, state: TrainState, batch: Any, key: Any) -> tuple[TrainState, dict[str, jax.Array]]:
        """One update ([T-2]..[T-7]); returns the new state and the metrics of this step."""
        self._check_state(state)
        obs, actions = self.check_batch(batch)
        return self.jitted(state, obs, actions, _check_key(key))

    def loss(self, params: Any, batch: Any, key: Any) -> jax.Array:
        """Batch loss ([L-3]) of ``params`` on ``batch`` with the draws of ``key`` ([T-2], [T-4])."""
        self._check_params("params", params)
        obs, actions = self.check_batch(batch)
        return _loss_jit(self._spec, self._tables, params, self._rest, obs, actions, _check_key(key))[0]

    def draw(self, key: Any, batch_size: int) -> dict[str, jax.Array]:
        """The per-example draws of a step with ``key`` ([T-2], [T-3]).

        ``{"delay": [B] int32, "tau": [B], "noise": [B, H, A], "weights": [B, H]}``,
        exactly what :meth:`__call__` uses for a batch of ``batch_size`` examples.
        """
        batch_size = check_int("batch_size", batch_size, 1, MAX_BATCH)
        return _draw_jit(self._spec, self._tables, _check_key(key), batch_size)

    def policy(self, state: TrainState) -> FlowPolicy:
        """A new :class:`FlowPolicy` holding ``state``'s parameters."""
        self._check_state(state)
        return nnx.merge(self._spec.graphdef, state.params, self._rest)


def _tables(config: TrainConfig, H: int, weight_table: jax.Array, probs: jax.Array) -> tuple:
    """Traced inputs of the step: (weights per delay [H + 1, H], CDF padded to [H + 1], d_min)."""
    if config.method == "none":
        # A CDF of ones draws d = 0 for every u < 1: `none` runs the delay code path with w = 0.
        return weight_table, jnp.ones((H + 1,), jnp.float32), jnp.zeros((), jnp.int32)
    cdf = delay_cdf(probs)
    # Padding with 1 adds no counts (u < 1), and one CDF shape for every distribution avoids recompiles.
    cdf = jnp.concatenate([cdf, jnp.ones((H + 1 - cdf.shape[0],), jnp.float32)])
    return weight_table, cdf, jnp.asarray(config.d_min, jnp.int32)


def _weight_table(config: TrainConfig, H: int) -> jax.Array:
    """Weights of every delay 0 .. H for the method ([T-3], [W-7], [W-8], [W-9]); row d is used for delay d."""
    if config.method == "soft":
        window = config.window
        if window.rule.kind != "hard" and window.rule.bound() > H:
            raise ValueError(f"config.window endpoint bound (h_max or h) must be <= H={H} ([E-1]), "
                             f"got {window.rule.bound()}")
        # Built with the JAX weights module so training sees the weights the JAX samplers use.
        return _soft_table_jit(_jw.from_reference(window), H, config.execute_horizon)
    if config.method == "hard":
        return _hard_table_jit(H)
    return jnp.zeros((H + 1, H), jnp.float32)


# jit: the eager version dispatches dozens of small ops one by one.
_soft_table_jit = jax.jit(lambda window, H, s: _jw.weight_table(H, window, s), static_argnums=(1, 2))
_hard_table_jit = jax.jit(lambda H: jax.vmap(lambda d: _jw.hard_weights(H, d))(jnp.arange(H + 1, dtype=jnp.int32)),
                          static_argnums=0)


def make_train_step(policy: FlowPolicy, config: TrainConfig, *, check_finite: bool = True) -> TrainStep:
    """The train step of ``config`` for ``policy``'s architecture ([T-7]).

    ``step = make_train_step(policy, config)``; ``state = step.init_state()``;
    ``state, metrics = step(state, (obs, actions), key)``. ``check_finite=False``
    skips the host-side NaN/inf scan of each batch (shape checks remain).
    The policy itself is not modified; :meth:`TrainStep.policy` returns a new one.
    """
    return TrainStep(policy, config, check_finite=check_finite)


# --------------------------------------------------------------------------- loop


def _is_array_data(data: Any) -> bool:
    if isinstance(data, Mapping):
        return True
    return isinstance(data, tuple) and len(data) == 2 and all(hasattr(a, "shape") for a in data)


def _array_batches(step: TrainStep, data: Any, batch_size: int, key: jax.Array) -> Iterator[tuple]:
    """Shuffled minibatches without replacement, reshuffled every epoch from ``key`` ([T-9])."""
    obs, actions = step.check_batch(data)
    n = obs.shape[0]
    if n < batch_size:
        raise ValueError(f"config.batch_size must be an integer in [1, {n}] (the number of examples), "
                         f"got {batch_size}")
    take = jax.jit(lambda o, a, idx: (o[idx], a[idx]))
    per_epoch = n // batch_size  # the last partial batch is dropped so every step has the same shape
    epoch = 0
    while True:
        perm = jax.random.permutation(jax.random.fold_in(key, epoch), n)
        for b in range(per_epoch):
            yield take(obs, actions, perm[b * batch_size:(b + 1) * batch_size])
        epoch += 1


def train(policy: FlowPolicy, data: Any, config: TrainConfig, key: Any, num_steps: int,
          progress: bool = True) -> tuple[FlowPolicy, np.ndarray]:
    """Trains ``policy`` for ``num_steps`` steps; returns ``(trained policy, loss history [num_steps])`` ([T-9]).

    ``data`` is either arrays, ``(obs [N, O], actions [N, H, A])`` (a tuple) or
    ``{"obs": ..., "actions": ...}``, from which shuffled batches of
    ``config.batch_size`` are drawn epoch by epoch; or any other iterable of
    batches in those two forms (each validated; a batch-size change recompiles).
    Step ``i`` uses ``fold_in(k_steps, i)`` and shuffling uses ``k_data``, with
    ``k_data, k_steps = split(key)`` ([T-8]): same key and data give bitwise the
    same parameters. A tqdm bar is shown when ``progress`` and stderr is a TTY.
    The input policy is not modified.
    """
    step = make_train_step(policy, config)
    key = _check_key(key)
    num_steps = check_int("num_steps", num_steps, 1, MAX_STEPS)
    if not isinstance(progress, bool):
        raise ValueError(f"progress must be a bool, got {progress!r}")
    k_data, k_steps = jax.random.split(key)
    if _is_array_data(data):
        batches = _array_batches(step, data, config.batch_size, k_data)
        run = step.jitted  # batches were validated once, as arrays
    elif isinstance(data, Iterable) and not isinstance(data, (str, bytes)):
        batches = iter(data)
        run = None
    else:
        raise ValueError("data must be (obs, actions) arrays, a mapping with 'obs' and 'actions', or an "
                         f"iterable of such batches, got {type(data).__name__}")

    state = step.init_state()
    losses = []
    show = progress and sys.stderr.isatty()
    log_every = max(1, num_steps // 100)
    with tqdm(total=num_steps, disable=not show, desc=f"train[{config.method}]", leave=False) as bar:
        for i in range(num_steps):
            try:
                batch = next(batches)
            except StopIteration:
                raise ValueError(f"data ran out after {i} batches; num_steps={num_steps} needs more") from None
            k = jax.random.fold_in(k_steps, i)
            if run is None:
                state, metrics = step(state, batch, k)
            else:
                state, metrics = run(state, batch[0], batch[1], k)
            losses.append(metrics["loss"])
            if show and (i % log_every == 0 or i == num_steps - 1):
                bar.set_postfix(loss=f"{float(metrics['loss']):.4g}")  # syncs, hence only every few steps
            bar.update(1)
    history = np.asarray(jax.device_get(jnp.stack(losses)))
    return step.policy(state), history

