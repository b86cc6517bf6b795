"""Arm policy checkpoints: chapter-T checkpoint files with the arm metadata ([A-18], [A-21], [T-11], [T-12])."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from softrtc._files import package_data_dir
from softrtc.jax import methods as jmethods
from softrtc.jax import weights as jweights
from softrtc.jax.checkpoint import load_checkpoint, save_checkpoint
from softrtc.jax.policy import FlowPolicy
from softrtc.jax.training import TrainConfig
from softrtc.reference._validate import check_choice

from .env import ACTION_DIM
from .features import FEATURE_DIM, Normalizer
from .policies import ArmPolicy, check_parts
from .policy_config import STUDY_METHODS, TRAIN_METHODS, ArmPolicyConfig

__all__ = ["ARM_FORMAT", "CKPT_FILES", "save_arm_checkpoint", "load_arm_checkpoint", "default_checkpoint_dir",
           "load_policies"]

# The file of each training objective's checkpoint ([A-21]).
CKPT_FILES = {"naive": "base.npz", "train_hard": "train_hard.npz", "train_soft": "train_soft.npz"}
# Tag of the arm section in a chapter-T checkpoint's metadata ([A-18]).
ARM_FORMAT = "softrtc-arm-policy-2"


def save_arm_checkpoint(path, model: FlowPolicy, normalizer: Normalizer, config: ArmPolicyConfig,
                        method: str, meta: dict | None = None, train_config: TrainConfig | None = None) -> str:
    """Write an arm policy as a chapter-T checkpoint ([A-18], [T-11]).

    ``softrtc.jax.checkpoint.save_checkpoint`` stores the parameters; its
    metadata holds ``{"arm": {"format": ARM_FORMAT, "method", "config",
    "normalizer", "train_config", "meta"}}`` (all JSON).
    """
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path).endswith(".npz"):
        raise ValueError(f"path must be a str or PathLike ending in '.npz', got {path!r}")
    check_parts(model, normalizer, config)
    method = check_choice("method", method, TRAIN_METHODS)
    if meta is not None and not isinstance(meta, dict):
        raise ValueError(f"meta must be a dict or None, got {type(meta).__name__}")
    if train_config is not None and not isinstance(train_config, TrainConfig):
        raise ValueError(f"train_config must be a TrainConfig or None, got {type(train_config).__name__}")
    arm = {"format": ARM_FORMAT, "method": method, "config": dataclasses.asdict(config),
           "normalizer": normalizer.to_dict(), "train_config": None if train_config is None else train_config.to_dict(),
           "meta": meta or {}}
    save_checkpoint(path, model, {"arm": arm})
    return os.fspath(path)


def load_arm_checkpoint(path, sampler_method: str | None = None) -> ArmPolicy:
    """Load a checkpoint written by :func:`save_arm_checkpoint` into an :class:`ArmPolicy` ([A-18], [T-12]).

    ``sampler_method`` (default: the method the checkpoint was trained with)
    selects the chunk generator ([S-6]); e.g. ``inference_soft`` on the base.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint .npz file, got {path!r}")
    if sampler_method is not None:
        check_choice("sampler_method", sampler_method, jmethods.METHODS)
    model, metadata = load_checkpoint(path)
    arm = metadata.get("arm") if isinstance(metadata, dict) else None
    if not isinstance(arm, dict) or arm.get("format") != ARM_FORMAT:
        raise ValueError(f"path {os.fspath(path)!r} is not a softrtc arm checkpoint (no '{ARM_FORMAT}' metadata)")
    try:
        config = ArmPolicyConfig(**arm["config"])
        norm = Normalizer.from_dict(arm["normalizer"])
        method = check_choice("method", arm["method"], TRAIN_METHODS)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"path {os.fspath(path)!r}: invalid arm metadata ({exc})") from exc
    if model.config != config.policy_config() or model.obs_dim != FEATURE_DIM or model.action_dim != ACTION_DIM:
        raise ValueError(f"path {os.fspath(path)!r}: stored policy does not match its arm config")
    window = None
    if (sampler_method or method) == "train_soft" and isinstance(arm.get("train_config"), dict):
        # The training window is the inference window ([W-7]): run the sampler with the one stored.
        try:
            window = jweights.from_reference(TrainConfig.from_dict(arm["train_config"]).window)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"path {os.fspath(path)!r}: invalid train_config in arm metadata ({exc})") from exc
    pol = ArmPolicy(model, norm, config, sampler_method or method, trained_as=method, meta=arm.get("meta", {}),
                    window=window)
    pol.train_config = arm.get("train_config")
    return pol



def default_checkpoint_dir() -> Path:
    """The shipped checkpoints: package data ``softrtc/arm/checkpoints`` ([A-21])."""
    return package_data_dir("softrtc.arm", "checkpoints")


def load_policies(checkpoint_dir=None, methods=STUDY_METHODS) -> dict:
    """``{method: ArmPolicy}`` from ``base.npz``, ``train_hard.npz``, ``train_soft.npz`` ([A-21]).

    Method ``naive`` and the inference-time methods use the base checkpoint.
    """
    if checkpoint_dir is not None and not isinstance(checkpoint_dir, (str, os.PathLike)):
        raise ValueError(f"checkpoint_dir must be a str, PathLike or None, got {checkpoint_dir!r}")
    if isinstance(methods, str) or not hasattr(methods, "__iter__"):
        raise ValueError(f"methods must be a sequence of method names, got {methods!r}")
    folder = Path(default_checkpoint_dir() if checkpoint_dir is None else checkpoint_dir)
    if not folder.is_dir():
        raise ValueError(f"checkpoint_dir must be an existing folder, got {str(folder)!r}")
    methods = list(methods)
    if not methods:
        raise ValueError("methods must be a non-empty sequence of method names")
    for m in methods:
        check_choice("methods entry", m, jmethods.METHODS)
    out = {}
    for m in methods:
        f = folder / CKPT_FILES.get(m, "base.npz")
        if not f.is_file():
            raise ValueError(f"checkpoint {str(f)!r} is missing; run `softrtc arm train --out {folder}`")
        pol = load_arm_checkpoint(f, sampler_method=m)
        # Each file holds the role its name says: a fine-tune copied over base.npz would otherwise run
        # as the base, under the base's label, without notice.
        role = "train_hard" if m == "train_hard" else "train_soft" if m == "train_soft" else "naive"
        if pol.trained_as != role:
            raise ValueError(f"checkpoint {str(f)!r} was trained as {pol.trained_as!r} (its stored training "
                             f"method), but {f.name} must hold the policy trained as {role!r}, which method "
                             f"{m!r} runs")
        out[m] = pol
    return out
