"""A PyTorch flow policy on the arm sorting task, trained and evaluated as the JAX arm policies are ([PT-9]).

Same data, features and recipe as ``softrtc.arm`` ([A-15]..[A-20]): DART demonstrations of the scripted
expert (``generate_demos(episodes, seed, noise_std)``), the policy input and per-dimension normalization
of [A-17] / [A-18], chunks of the next H = 10 labels; a base trained by plain flow matching for ``steps``
with seed ``seed``, then Train Hard and Train Soft RTC fine-tunes from the base for ``finetune_steps``
with seeds ``seed + 1`` and ``seed + 2`` at a third of the learning rate; delays uniform on
``0 .. min(s, H - s)``, the default window of [W-7]; AdamW (weight decay 1e-4 on kernels, clipping at 1),
linear warm-up over ``min(200, steps // 10)`` steps then cosine decay to 5 % ([T-6]); batch 128, batches
drawn without replacement per epoch. The network is :class:`softrtc.torch.policy.FlowPolicy` with the JAX arm
policy's architecture and sizes (chapter P, ``ARM_POLICY``); inference uses
the precomputed-conditioning samplers of ``softrtc.torch.sampler`` ([PT-6]).

Evaluation (:func:`evaluate`): every policy (the PyTorch ones and the shipped JAX checkpoints) runs in the
arm's simulated-delay executor (``softrtc.arm.executor.run_simulated_episode``, [A-22]) on the same
environment seeds ``seed0 .. seed0 + episodes - 1`` with the same sampler key per seed (paired episodes),
at each constant delay.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from softrtc._files import check_out_dir, read_json, write_json

from . import _validate as v
from .methods import METHODS, method_weights
from .policy import FlowPolicy, PolicyConfig
from .sampler import conditioning_table, naive_sample_conditioned, rtc_sample_conditioned, step_conditioning
from .training import RTCObjective

__all__ = ["ARM_POLICY", "TrainRecipe", "ArmTorchPolicy", "train_policy", "train_arm_policies", "evaluate",
           "summarize", "format_table", "write_results", "read_results", "OBJECTIVE"]

# The PyTorch policy for the arm: the JAX arm policy's network (chapter P, adaLN) with its sizes ([A-17]), so
# the comparison is at equal architecture.
ARM_POLICY = PolicyConfig(horizon=10, width=128, channel_hidden=256, token_hidden=32, num_layers=2,
                          architecture="adaln")
OBJECTIVE = {"naive": "none", "train_hard": "hard", "train_soft": "soft"}
STUDY = ("naive", "train_hard", "train_soft")
LABELS = {"naive": "Base", "train_hard": "Train Hard RTC", "train_soft": "Train Soft RTC"}


def _arm():
    """The arm package's features, normalizer, config and data helpers (imported when used)."""
    from softrtc.arm import demos, env, executor
    from softrtc.arm.features import FEATURE_DIM, Normalizer, action_bounds, policy_features
    from softrtc.arm.policy_config import ArmPolicyConfig
    from softrtc.arm.training import chunk_dataset
    return dict(demos=demos, env=env, executor=executor, FEATURE_DIM=FEATURE_DIM, Normalizer=Normalizer,
                action_bounds=action_bounds, policy_features=policy_features, ArmPolicyConfig=ArmPolicyConfig,
                chunk_dataset=chunk_dataset)


@dataclasses.dataclass(frozen=True)
class TrainRecipe:
    """The JAX arm recipe's numbers ([A-20], [T-6]); every field validated ([N-7])."""

    episodes: int = 400
    noise_std: float = 0.03
    steps: int = 4000
    finetune_steps: int = 800
    batch_size: int = 128
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    grad_clip: float = 1.0
    final_lr_ratio: float = 0.05
    seed: int = 0

    def __post_init__(self):
        v.integer("episodes", self.episodes, 1, 100000)
        v.real("noise_std", self.noise_std, 0.0, 1.0)
        v.integer("steps", self.steps, 1, 10**7)
        v.integer("finetune_steps", self.finetune_steps, 1, 10**7)
        v.integer("batch_size", self.batch_size, 1, 1 << 16)
        v.real("learning_rate", self.learning_rate, 0.0, 1.0, lo_open=True)
        v.real("weight_decay", self.weight_decay, 0.0, 10.0)
        v.real("grad_clip", self.grad_clip, 0.0, math.inf, lo_open=True)
        v.real("final_lr_ratio", self.final_lr_ratio, 0.0, 1.0)
        v.integer("seed", self.seed, 0, 2**31 - 3)


def lr_factor(step: int, steps: int, final_ratio: float) -> float:
    """Linear warm-up from 0 over min(200, steps // 10) steps, then cosine decay to final_ratio at ``steps`` ([T-6])."""
    warm = min(200, steps // 10)
    if step < warm:
        return step / warm
    frac = min(1.0, (step - warm) / max(steps - warm, 1))
    return final_ratio + (1.0 - final_ratio) * 0.5 * (1.0 + math.cos(math.pi * frac))


def train_policy(model: FlowPolicy, obs: torch.Tensor, chunks: torch.Tensor, method: str, steps: int, seed: int,
                 lr: float, recipe: TrainRecipe, s: int, progress=None) -> np.ndarray:
    """Train ``model`` in place with the objective of ``method`` ([PT-4]); returns the per-step losses.

    Every draw (epoch shuffles, delays, flow times, noise) comes from ``torch.Generator().manual_seed(seed)``.
    The base objective (``naive``) calls the model with one time per example ``t [B]`` ([T-5]).
    """
    v.choice("method", method, tuple(OBJECTIVE))
    steps = v.integer("steps", steps, 1, 10**7)
    seed = v.integer("seed", seed, 0, 2**31 - 1)
    H = model.H
    obj = RTCObjective(OBJECTIVE[method], H, s, d_max=min(s, H - s))
    g = torch.Generator().manual_seed(seed)
    decay = [p for p in model.parameters() if p.dim() >= 2]
    rest = [p for p in model.parameters() if p.dim() < 2]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": recipe.weight_decay},
                             {"params": rest, "weight_decay": 0.0}], lr=lr, betas=(0.9, 0.999), eps=1e-8)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: lr_factor(k, steps, recipe.final_lr_ratio))
    N, B = obs.shape[0], recipe.batch_size
    if N < B:
        raise ValueError(f"the dataset must hold at least batch_size={B} examples, got {N}")
    order, pos = torch.randperm(N, generator=g), 0
    losses = np.zeros(steps)
    model.train()
    for k in range(steps):
        if pos + B > N:  # a new epoch; the last partial batch is dropped
            order, pos = torch.randperm(N, generator=g), 0
        idx = order[pos:pos + B]
        pos += B
        a, o = chunks[idx], obs[idx]
        b = obj.draw(a, g)
        t = b["tau"] if method == "naive" else b["times"]
        loss = obj.loss(model(o, b["x"], t), a, b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), recipe.grad_clip)
        opt.step()
        sched.step()
        losses[k] = float(loss.detach())
        if progress and (k + 1) % 500 == 0:
            progress(f"{method}: step {k + 1}/{steps}, loss {losses[max(0, k - 99):k + 1].mean():.4f}")
    model.eval()
    return losses


def _seed_of(key) -> int:
    """A torch seed from the executor's JAX key for this request (its key data), so requests differ and
    the same (env seed, request) draws the same noise for every policy."""
    import jax

    data = np.asarray(jax.random.key_data(key), np.uint64).ravel()
    return int(data[0] << np.uint64(32) | data[-1]) % (2**63 - 1)


class ArmTorchPolicy:
    """A trained FlowPolicy with its normalizer and chunk generator, shaped like ``softrtc.arm``'s ArmPolicy.

    ``generate(obs, prior, d, key)`` returns a chunk ``[H, 4]`` in physical units clipped to the action
    ranges ([A-19]); the first chunk (prior None) is naive with d = 0 ([X-2]); later chunks use
    ``method``'s sampler ([S-6]) with every delay's time conditioning precomputed ([PT-6]). The noise is
    drawn from a torch generator seeded from ``key``.
    """

    def __init__(self, model: FlowPolicy, normalizer, method: str, execute_horizon: int = 5, num_steps: int = 5):
        A = _arm()
        if not isinstance(model, FlowPolicy):
            raise ValueError(f"model must be a softrtc.torch FlowPolicy, got {type(model).__name__}")
        if not isinstance(normalizer, A["Normalizer"]):
            raise ValueError(f"normalizer must be a softrtc.arm Normalizer, got {type(normalizer).__name__}")
        self.method = v.choice("method", method, METHODS)
        self.model, self.normalizer = model.eval(), normalizer
        self.H, self.s = model.H, v.integer("execute_horizon", execute_horizon, 1, model.H - 1)
        self.T = v.integer("num_steps", num_steps, 1, 64)
        self.max_delay = min(self.s, self.H - self.s)
        self.low, self.high = A["action_bounds"]()
        self._features = A["policy_features"]
        f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        self._nm = [f32(normalizer.obs_mean), f32(normalizer.obs_std), f32(normalizer.act_mean),
                    f32(normalizer.act_std)]
        with torch.no_grad():
            self._naive = step_conditioning(model, torch.zeros(1, 1), self.T)
            if method in ("train_hard", "train_soft"):
                self._table = torch.stack([method_weights(method, self.H, self.s, d) for d in range(self.max_delay + 1)])
                self._cond = conditioning_table(model, self._table, self.T)

    def generate(self, obs, prior, d, key) -> np.ndarray:
        o = np.asarray(obs, np.float64)
        if o.shape != (34,) or not np.all(np.isfinite(o)):
            raise ValueError(f"obs must be a finite vector of shape [34], got shape {list(o.shape)}")
        feat = (torch.as_tensor(self._features(o), dtype=torch.float32) - self._nm[0]) / self._nm[1]
        g = torch.Generator().manual_seed(_seed_of(key))
        noise = torch.randn(1, self.H, 4, generator=g)
        with torch.no_grad():
            if prior is None:
                v.integer("d", d, 0, 0)
                z = naive_sample_conditioned(self.model, feat[None], noise, self.T, self._naive)
            else:
                d = v.integer("d", d, 0, self.max_delay)
                y = (torch.as_tensor(np.asarray(prior), dtype=torch.float32) - self._nm[2]) / self._nm[3]
                v.shape("prior", y, expected=(self.H, 4))
                if self.method in ("train_hard", "train_soft"):
                    z = rtc_sample_conditioned(self.model, feat[None], noise, y[None], self._table[d], self.T,
                                               self._cond[d])
                elif self.method == "naive":
                    z = naive_sample_conditioned(self.model, feat[None], noise, self.T, self._naive)
                else:
                    from .methods import generate_chunk
                    z = generate_chunk(self.method, self.model, feat[None], noise, y[None], self.s, d, self.T)
        chunk = (z[0] * self._nm[3] + self._nm[2]).double().numpy()
        return np.clip(chunk, self.low, self.high)


def _save(path: Path, model: FlowPolicy, meta: dict) -> None:
    torch.save({"state_dict": model.state_dict(), "meta": {**meta, "policy": dataclasses.asdict(model.config)}}, path)


def _trained_with(path: Path) -> dict | None:
    """The policy config a saved policy was trained with (None for a file that does not record it)."""
    return torch.load(path, weights_only=True)["meta"].get("policy")


def _load(path: Path) -> tuple:
    blob = torch.load(path, weights_only=True)
    if blob["meta"].get("policy") != dataclasses.asdict(ARM_POLICY):
        raise ValueError(f"{str(path)!r} holds a policy trained with another network than ARM_POLICY "
                         f"({blob['meta'].get('policy')}); retrain with `softrtc arm torch --retrain`")
    model = FlowPolicy(blob["meta"]["obs_dim"], 4, ARM_POLICY, generator=torch.Generator().manual_seed(0))
    model.load_state_dict(blob["state_dict"])
    return model, blob["meta"]


def train_arm_policies(work_dir, recipe: TrainRecipe = TrainRecipe(), demos=None, progress=print) -> dict:
    """Demos, base, Train Hard and Train Soft fine-tunes saved to ``work_dir`` ([PT-9]); returns a summary
    with the normalizer and the losses. ``demos``: an existing ``generate_demos`` file made with
    (recipe.episodes, recipe.seed, recipe.noise_std), or None to generate one in a temporary folder."""
    A = _arm()
    if not isinstance(recipe, TrainRecipe):
        raise ValueError(f"recipe must be a TrainRecipe, got {type(recipe).__name__}")
    out = check_out_dir("work_dir", work_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if demos is None:
        with tempfile.TemporaryDirectory(prefix="softrtc-torch-demos-") as tmp:
            A["demos"].generate_demos(recipe.episodes, recipe.seed, recipe.noise_std, os.path.join(tmp, "d.npz"))
            data = A["demos"].load_demos(os.path.join(tmp, "d.npz"))
    else:
        data = A["demos"].load_demos(os.fspath(demos))
        got = (len(data["episode_start"]), int(data["seed"]), float(data["noise_std"]))
        if got[:2] != (recipe.episodes, recipe.seed) or not math.isclose(got[2], recipe.noise_std, rel_tol=1e-6):
            raise ValueError(f"demos file holds (episodes, seed, noise_std) = {got}, expected "
                             f"{(recipe.episodes, recipe.seed, recipe.noise_std)}")
    progress(f"demos: {len(data['episode_start'])} episodes, {len(data['obs'])} steps "
             f"({time.perf_counter() - t0:.0f} s)")
    cfg = A["ArmPolicyConfig"]()
    ds = A["chunk_dataset"](data, cfg.horizon)
    norm = A["Normalizer"].fit(A["policy_features"](data["obs"]), data["action"])
    obs = torch.as_tensor(norm.obs(A["policy_features"](ds["obs"])), dtype=torch.float32)
    chunks = torch.as_tensor(norm.act(ds["chunks"]), dtype=torch.float32)
    s = cfg.execute_horizon
    model = FlowPolicy(A["FEATURE_DIM"], 4, ARM_POLICY, generator=torch.Generator().manual_seed(recipe.seed))
    summary = {"recipe": dataclasses.asdict(recipe), "normalizer": norm.to_dict(), "losses": {}}
    meta = {"obs_dim": A["FEATURE_DIM"], "normalizer": norm.to_dict(), "recipe": dataclasses.asdict(recipe)}
    losses = train_policy(model, obs, chunks, "naive", recipe.steps, recipe.seed, recipe.learning_rate, recipe, s,
                          progress)
    _save(out / "base.pt", model, {**meta, "method": "naive"})
    summary["losses"]["naive"] = [float(losses[:100].mean()), float(losses[-100:].mean())]
    progress(f"base: loss {losses[:100].mean():.4f} -> {losses[-100:].mean():.4f} ({time.perf_counter() - t0:.0f} s)")
    for i, m in enumerate(("train_hard", "train_soft")):
        ft, _ = _load(out / "base.pt")
        losses = train_policy(ft, obs, chunks, m, recipe.finetune_steps, recipe.seed + 1 + i,
                              recipe.learning_rate / 3, recipe, s, progress)
        _save(out / f"{m}.pt", ft, {**meta, "method": m})
        summary["losses"][m] = [float(losses[:100].mean()), float(losses[-100:].mean())]
        progress(f"{m}: loss {losses[:100].mean():.4f} -> {losses[-100:].mean():.4f} "
                 f"({time.perf_counter() - t0:.0f} s)")
    return summary


def load_arm_policies(work_dir) -> dict:
    """``{method: ArmTorchPolicy}`` from the files of :func:`train_arm_policies`."""
    A = _arm()
    out = {}
    for m in STUDY:
        f = Path(work_dir) / ("base.pt" if m == "naive" else f"{m}.pt")
        if not f.is_file():
            raise ValueError(f"{str(f)!r} is missing; train with `softrtc arm torch --work {work_dir}`")
        model, meta = _load(f)
        out[m] = ArmTorchPolicy(model, A["Normalizer"].from_dict(meta["normalizer"]), m)
    return out


METRICS = ("success", "completion", "throughput", "D1", "D2", "D3", "boundary")


def evaluate(policies: dict, delays, episodes: int, seed0: int = 10_000, max_steps: int | None = None,
             progress=print) -> list:
    """Paired episodes ([PT-9]): for each delay, each env seed ``seed0 + i`` and each policy, one simulated-delay
    episode with constant delay ``d`` and key ``jax.random.key(seed0 + i)``. Returns one record per episode."""
    import jax

    A = _arm()
    if not isinstance(policies, dict) or not policies:
        raise ValueError("policies must be a non-empty dict {name: policy}")
    episodes = v.integer("episodes", episodes, 1, 100000)
    seed0 = v.integer("seed0", seed0, 0, 2**31 - 1 - episodes)
    rows = []
    for d in delays:
        for i in range(episodes):
            for name, pol in policies.items():
                rec = A["executor"].run_simulated_episode(pol, seed0 + i, d, jax.random.key(seed0 + i),
                                                          max_steps=max_steps)
                m = A["executor"].episode_metrics(rec)
                rows.append({"policy": name, "delay": int(d), "env_seed": seed0 + i, "steps": rec.steps,
                             **{k: (float(m[k]) if m[k] is not None else float("nan")) for k in METRICS}})
            progress(f"d={d}: episode {i + 1}/{episodes}")
    return rows


def _bootstrap(x: np.ndarray, rng: np.random.Generator, n: int = 2000) -> tuple:
    """95 % percentile bootstrap interval of the mean."""
    idx = rng.integers(0, len(x), size=(n, len(x)))
    means = x[idx].mean(1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def summarize(rows: list, seed: int = 0) -> list:
    """Per (policy, delay): mean and 95 % bootstrap interval of each metric over its episodes (finite values),
    and the paired difference of success and throughput against the JAX policy of the same method."""
    rng = np.random.default_rng(seed)
    out = []
    keys = sorted({(r["policy"], r["delay"]) for r in rows}, key=lambda k: (k[1], k[0]))
    for pol, d in keys:
        sel = [r for r in rows if r["policy"] == pol and r["delay"] == d]
        entry = {"policy": pol, "delay": d, "episodes": len(sel)}
        for k in METRICS:
            x = np.array([r[k] for r in sel], np.float64)
            x = x[np.isfinite(x)]
            entry[k] = [float(x.mean()), *_bootstrap(x, rng)] if x.size else [float("nan")] * 3
        out.append(entry)
    return out


def format_table(summary: list) -> str:
    """The README table: one line per delay and policy, mean [95 % interval]."""
    head = f"{'d':>2s}  {'policy':<22s}{'success':>22s}{'throughput (obj/min)':>26s}{'D2':>28s}{'boundary':>28s}"
    lines = [head, "-" * len(head)]
    fmt = lambda e, k, p: f"{e[k][0]:.{p}f} [{e[k][1]:.{p}f}, {e[k][2]:.{p}f}]"  # noqa: E731
    for e in summary:
        lines.append(f"{e['delay']:>2d}  {e['policy']:<22s}{fmt(e, 'success', 2):>22s}{fmt(e, 'throughput', 2):>26s}"
                     f"{fmt(e, 'D2', 4):>28s}{fmt(e, 'boundary', 4):>28s}")
    return "\n".join(lines)


def write_results(path, result: dict) -> None:
    """The experiment's result (recipe, protocol, losses, episodes, summary) as JSON, written whole."""
    write_json(path, result, prefix=".arm-torch-", allow_nan=True)


def read_results(path) -> dict:
    """A result file of :func:`write_results`; the summary is recomputed from its episodes."""
    res = read_json(path, "result file")
    if not isinstance(res, dict) or "episodes" not in res or "protocol" not in res:
        raise ValueError(f"{os.fspath(path)!r} is not a softrtc arm torch result")
    res["summary"] = summarize(res["episodes"], res["protocol"].get("bootstrap_seed", 0))
    return res


@dataclasses.dataclass(frozen=True)
class Protocol:
    """The evaluation protocol of [PT-9]: constant delays, paired episodes per delay, their env seeds."""

    delays: tuple = (1, 3, 5)
    episodes: int = 20
    seed0: int = 10_000
    max_steps: int | None = None
    bootstrap_seed: int = 0

    def __post_init__(self):
        if not isinstance(self.delays, tuple) or not self.delays:
            raise ValueError(f"delays must be a non-empty tuple, got {self.delays!r}")
        for d in self.delays:
            v.integer("delays entry", d, 0, 5)
        v.integer("episodes", self.episodes, 1, 100000)
        v.integer("seed0", self.seed0, 0, 2**31 - 1 - self.episodes)
        if self.max_steps is not None:
            from softrtc.arm.geometry import ArmConfig  # the arm extra; only a given limit needs it

            # The executor runs at most the scene's own episode length: a larger limit fails there, after training.
            v.integer("max_steps", self.max_steps, 1, ArmConfig().max_steps)
        v.integer("bootstrap_seed", self.bootstrap_seed, 0, 2**31 - 1)


def run_experiment(out, work, recipe: TrainRecipe = TrainRecipe(), protocol: Protocol = Protocol(), demos=None,
                   retrain: bool = False, progress=print) -> dict:
    """Train the PyTorch policies (unless ``work`` holds them and not ``retrain``), evaluate them and the
    shipped JAX checkpoints under ``protocol``, write ``out`` (JSON) and return the result ([PT-9])."""
    from softrtc.arm.checkpoints import load_policies as load_jax
    if not isinstance(protocol, Protocol):
        raise ValueError(f"protocol must be a Protocol, got {type(protocol).__name__}")
    if not isinstance(out, (str, os.PathLike)) or not os.fspath(out).endswith(".json"):
        raise ValueError(f"out must be a path ending in .json, got {out!r}")
    work = check_out_dir("work", work)  # '' would put the policies in the current folder
    t0 = time.perf_counter()
    trained = None
    files = [work / f for f in ("base.pt", "train_hard.pt", "train_soft.pt")]
    # policies trained with another network (an earlier ARM_POLICY) are trained again
    if retrain or not all(f.is_file() for f in files) \
            or any(_trained_with(f) != dataclasses.asdict(ARM_POLICY) for f in files):
        trained = train_arm_policies(work, recipe, demos, progress)
    pols = {f"torch {LABELS[m]}": p for m, p in load_arm_policies(work).items()}
    jax_pols = load_jax()
    for m in STUDY:
        jax_pols[m].warmup()
        pols[f"jax {LABELS[m]}"] = jax_pols[m]
    rows = evaluate(pols, protocol.delays, protocol.episodes, protocol.seed0, protocol.max_steps, progress)
    meta = json.loads((work / "summary.json").read_text()) if trained is None and (work / "summary.json").is_file() \
        else trained
    if trained is not None:
        (work / "summary.json").write_text(json.dumps(trained))
    res = {"recipe": dataclasses.asdict(recipe), "protocol": dataclasses.asdict(protocol),
           "policy": dataclasses.asdict(ARM_POLICY), "training": meta, "episodes": rows,
           "env": {"torch": torch.__version__, "threads": torch.get_num_threads()},
           "seconds": time.perf_counter() - t0}
    res["summary"] = summarize(rows, protocol.bootstrap_seed)
    write_results(out, res)
    return res
