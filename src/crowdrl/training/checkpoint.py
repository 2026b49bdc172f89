"""Atomic checkpoints with a config fingerprint, so a resume never mixes runs, and the loading of a
trained network (and its planner's predictor) from a run folder or a ``best.pt`` for evaluation or export.

A checkpoint holds tensors and plain containers only (dict, list, tuple, str, int, float, bool,
None), and is always loaded with ``torch.load(weights_only=True)``: a file carrying any other
pickled object (which could run code when unpickled) is refused, never executed.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import re
from collections import OrderedDict
from pathlib import Path
from typing import Any

import torch

from crowdrl.files import atomic_write_bytes
from crowdrl.sim.config import (LIDAR_KEYS, MIXED, OBSTACLE_KEYS, OPEN_SCENARIOS, SHARE_KEYS, SOCIAL_FORCE_KEYS,
                                CrowdConfig)
from crowdrl.training.compat import stored_config
from crowdrl.training.config import LEVERS_OFF, ConfigError, RunConfig, to_dict
from crowdrl.training.validation import validate

FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint is missing, truncated, of another format, or from another config."""


# Keys at the value that leaves the problem unchanged (no variable crowd, blind ORCA humans, no mixed shares):
# left out of the fingerprint at that value, so a stored config without them keeps its fingerprint.
_NEUTRAL = {"encoder": {"lidar": "off"},  # no scan read: hashed as before the key
            "env": {"min_humans": None, "max_humans": None, "mix": {}, "human_model": CrowdConfig.human_model,
                    "robot_visible": CrowdConfig.robot_visible,
                    **{k: getattr(CrowdConfig, k) for k in (*SOCIAL_FORCE_KEYS, *SHARE_KEYS)}}}


# The exploration keys there were when strategies came to own their keys: hashed at any value, as then, so stored
# checkpoints keep their fingerprints. A key a strategy's schema gains since is hashed only under that strategy
# and off its default: a key added at its default changes no fingerprint.
FINGERPRINTED_EXPLORATION = ("name", "eps_start", "eps_end", "anneal_frames", "dropout_start", "dropout_end", "sigma0",
                             "beta", "beta_end", "beta_schedule", "beta_decay", "reward_norm", "reward_center",
                             "reward_clip", "obs_norm", "obs_clip", "terminal_value", "icm_lr", "icm_feature_norm",
                             "icm_detach_target", "re3_k")

_TRAIN_NEUTRAL = LEVERS_OFF  # the levers off (not today's defaults): as before the keys


def config_fingerprint(config: dict) -> str:
    """Hash of the parts of a config that define the learning problem (not budgets or logging)."""
    return hashlib.sha256(json.dumps(fingerprinted(config), sort_keys=True).encode()).hexdigest()[:16]


def fingerprint_differences(current: dict, stored: dict) -> list[str]:
    """``key: <current> here, <stored> in the checkpoint`` for each key of :func:`fingerprinted` whose
    value differs between two configs (``to_dict`` form), in key order."""
    def flat(tree: Any, prefix: str = "") -> dict[str, Any]:
        if not isinstance(tree, dict):
            return {prefix: tree}
        return {k: v for key, sub in tree.items() for k, v in flat(sub, f"{prefix}{key}.").items()} or {prefix: {}}

    a, b = ({k.rstrip("."): v for k, v in flat(fingerprinted(c)).items()} for c in (current, stored))
    missing = "(not set)"
    return [f"{k}: {a.get(k, missing)!r} here, {b.get(k, missing)!r} in the checkpoint"
            for k in sorted(a.keys() | b.keys()) if a.get(k, missing) != b.get(k, missing)]


def fingerprinted(config: dict) -> dict[str, Any]:
    """The parts of a config (``to_dict`` form) that :func:`config_fingerprint` hashes."""
    keep = {k: config[k] for k in ("env", "encoder", "exploration", "seed") if k in config}
    for group, neutral in _NEUTRAL.items():
        if group in keep:
            keep[group] = {k: v for k, v in keep[group].items() if not (k in neutral and v == neutral[k])}
    if isinstance(keep.get("exploration"), dict):
        from crowdrl.exploration.strategy import owned_keys

        section = keep["exploration"]
        owned = owned_keys(str(section.get("name")))
        keep["exploration"] = {k: v for k, v in section.items()
                               if k in FINGERPRINTED_EXPLORATION or (k in owned and v != owned[k])}
    if "env" in keep:  # the ORCA backend changes speed, not numbers; obstacle geometry nothing in open space;
        # the lidar keys nothing without a scan (runs recorded before them had none); the social-force
        # parameters nothing unless some humans follow that model (social_force, or mixed with a share of it)
        social_force = keep["env"].get("human_model", "orca") == "social_force" or (
            keep["env"].get("human_model") == MIXED and keep["env"].get("social_force_share", 0.0) > 0)
        drop = {"orca_backend", *(OBSTACLE_KEYS if keep["env"].get("scenario") in OPEN_SCENARIOS else ()),
                *(LIDAR_KEYS if not keep["env"].get("lidar_rays") else ()),
                *(SOCIAL_FORCE_KEYS if not social_force else ())}
        keep["env"] = {k: v for k, v in keep["env"].items() if k not in drop}
    train = dict(config.get("train", {}))
    if isinstance(train.get("counterfactual"), dict) and train["counterfactual"].get("mode", "off") == "off":
        train.pop("counterfactual")  # off: hashed as a config without the key
    if isinstance(train.get("demonstrations"), dict) and train["demonstrations"].get("cases", 0) == 0:
        train.pop("demonstrations")  # off: hashed as a config without the key
    for key, off in _TRAIN_NEUTRAL.items():  # a stability lever off: hashed as a config without its key
        if key in train and train[key] == off:
            train.pop(key)
    for k in ("total_frames", "val_every_frames", "checkpoint_every_frames", "save_buffer", "test_episodes",
              "val_episodes", "compile_acting", "keep_val_checkpoints"):  # compile_acting: speed, and float rounding of Q
        train.pop(k, None)
    keep["train"] = train
    if config.get("planning", {}).get("enabled"):  # planning off: hashed as a config without the section
        # the safety check and the progress bias off: hashed as a planner without the key
        keep["planning"] = {k: v for k, v in config["planning"].items()
                            if not (k in ("safety_horizon", "progress_bias") and v == 0)}
    return keep


# what ``torch.load(weights_only=True)`` rebuilds without running code (exact types: a subclass such
# as a namedtuple or an OmegaConf node pickles its class, which the safe loader refuses)
_PLAIN = (dict, OrderedDict, list, tuple, str, int, float, bool, type(None), torch.Tensor, torch.nn.Parameter,
          torch.Size, torch.dtype, torch.device)


def check_plain(value: Any, where: str = "payload") -> None:
    """Raise ``TypeError`` naming the first entry of ``value`` that is not a tensor or plain container."""
    if type(value) not in _PLAIN:
        raise TypeError(f"checkpoint {where} is a {type(value).__module__}.{type(value).__qualname__}; checkpoints "
                        f"hold only tensors and plain containers (dict, list, tuple, str, int, float, bool, None), "
                        f"the types torch.load(weights_only=True) accepts")
    if isinstance(value, dict):
        for key, item in value.items():
            check_plain(key, f"{where} key {key!r}")
            check_plain(item, f"{where}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            check_plain(item, f"{where}[{i}]")


def merge_payload(payload: dict[str, Any], part: dict[str, Any], owner: str) -> None:
    """Add ``part``'s top-level checkpoint keys to ``payload``; ``KeyError`` naming ``owner`` for a key already there."""
    clash = sorted(set(part) & set(payload))
    if clash:
        raise KeyError(f"{owner} writes checkpoint keys already taken: {clash}")
    payload.update(part)


def rng_state() -> dict[str, Any]:
    """The global torch RNG states a checkpoint holds for an exact resume (``torch_rng``, ``cuda_rng``)."""
    return {"torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None}


def restore_rng(data: dict[str, Any]) -> None:
    """Set the global torch RNG states of a checkpoint (:func:`rng_state`'s keys)."""
    torch.set_rng_state(data["torch_rng"])
    if data.get("cuda_rng") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(data["cuda_rng"])


def save_checkpoint(path: Path, payload: dict[str, Any], fingerprint: str) -> None:
    """``torch.save`` the payload with format/fingerprint metadata, atomically.

    Raises ``TypeError`` naming the entry when the payload holds anything but tensors and plain
    containers (it could not be loaded back safely)."""
    import io

    check_plain(payload)
    buf = io.BytesIO()
    torch.save({"format": FORMAT_VERSION, "fingerprint": fingerprint, **payload}, buf)
    atomic_write_bytes(Path(path), buf.getvalue())


def load_checkpoint(path: Path, fingerprint: str | None = None, *, config: dict | None = None) -> dict[str, Any]:
    """Load (``weights_only=True``: nothing in the file is executed) and check a checkpoint; raise
    :class:`CheckpointError` naming the file and the reason otherwise: missing, truncated or corrupt,
    holding a Python object other than tensors and plain containers (refused unread), of another
    format, or (given ``fingerprint``) written by a run with another configuration: given ``config``
    too (the loading run's, ``to_dict`` form), the error names each key that differs, both values."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    if not is_torch_file(path):
        raise CheckpointError(f"{path} is not a crowdrl checkpoint (not a torch file: no zip or pickle header, "
                              f"e.g. a text file); give a run folder or its checkpoints/best.pt")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"GLOBAL ([\w.]+)", str(exc))
        if found:  # the safe unpickler met a class or function it does not rebuild, and ran nothing
            raise CheckpointError(
                f"{path} was refused: it holds a pickled Python object ({found.group(1)}), not only tensors and "
                f"plain containers, and unpickling it could run code. crowdrl never writes such a checkpoint "
                f"(it was crafted, or made by other code); nothing in it was run") from None
        detail = re.search(r"Unsupported [^\n.]*", str(exc))  # not torch's advice to load it unsafely
        raise CheckpointError(f"{path} is not a readable checkpoint (truncated or corrupt?): the safe loader "
                              f"cannot read it ({detail.group(0) if detail else 'not a torch file'})") from None
    except Exception as exc:
        raise CheckpointError(f"{path} is not a readable checkpoint (truncated or corrupt?): {_first_line(exc)}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT_VERSION:
        found = data.get("format") if isinstance(data, dict) else None
        raise CheckpointError(
            f"{path} is not a crowdrl checkpoint of format {FORMAT_VERSION} (found format "
            f"{'none' if found is None else found!r}, expected {FORMAT_VERSION}); this code reads format "
            f"{FORMAT_VERSION} only: load it with the crowdrl version that wrote it, or train the run again")
    if fingerprint is not None and data.get("fingerprint") != fingerprint:
        stored = data.get("config")
        differ = fingerprint_differences(config, stored) if isinstance(config, dict) and isinstance(stored, dict) else []
        if differ:
            raise CheckpointError(f"{path} was written by a run with another configuration; the keys that differ "
                                  f"(this run's config, e.g. its config.yaml, vs the checkpoint's): {'; '.join(differ)}")
        raise CheckpointError(
            f"{path} was written by a run with another configuration (fingerprint {data.get('fingerprint')} "
            f"!= {fingerprint}); resume it with its own config (see config.yaml in its run folder)"
        )
    return data


def val_checkpoint_name(frames: int) -> str:
    """The file name of the network kept at the validation after ``frames`` frames (``train.keep_val_checkpoints``):
    ``val-<frames, 9 digits>.pt``, so that names sort in training order."""
    return f"val-{frames:09d}.pt"


def val_checkpoints(run_dir: Path | str) -> list[Path]:
    """A run folder's validation checkpoints (``checkpoints/val-*.pt``), in training order."""
    return sorted(Path(run_dir, "checkpoints").glob("val-" + "[0-9]" * 9 + ".pt"))


def is_torch_file(path: Path | str) -> bool:
    """Whether ``path`` starts as a ``torch.save`` file does: a zip archive (the default format) or
    a pickle of protocol 2 or later (the legacy format)."""
    with open(path, "rb") as f:
        head = f.read(4)
    return head.startswith(b"PK\x03\x04") or (len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5)


def _first_line(exc: BaseException) -> str:
    lines = [line for line in str(exc).splitlines() if line.strip()]
    first = lines[0] if lines else ""
    return first if len(first) > 8 else f"{type(exc).__name__}: {first}".rstrip(": ")  # never a bare "105"


def check_finite_weights(module: torch.nn.Module, path: Path | str, what: str = "network") -> None:
    """Refuse (:class:`CheckpointError`, naming ``path`` and the first such parameter or buffer) a
    ``module`` loaded from ``path`` that holds NaN or infinite weights: it would be scored as if fine."""
    for name, value in module.state_dict().items():
        if torch.is_tensor(value) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            bad = int((~torch.isfinite(value)).sum())
            raise CheckpointError(f"{path}: the {what}'s {name!r} holds {bad} non-finite value(s) (NaN or inf) of "
                                  f"{value.numel()}; the checkpoint cannot be evaluated")


def checkpoint_path(path: Path | str) -> Path:
    """``path`` itself for a file; for a folder, a run folder's ``checkpoints/best.pt`` or a
    pretrained agent's ``best.pt`` (``pretrained/<name>``). A ``pretrained/<name>`` that does not
    exist raises :class:`CheckpointError` listing the agents that do."""
    path = Path(path)
    if not path.exists() and path.parent.name == "pretrained":
        have = sorted(f.parent.name for f in path.parent.glob("*/best.pt"))
        raise CheckpointError(f"no pretrained agent {path.name!r} in {path.parent}; "
                              f"available: {', '.join(have) or 'none'}")
    if not path.is_dir():
        return path
    return path / "best.pt" if (path / "best.pt").exists() and not (path / "checkpoints").exists() else \
        path / "checkpoints" / "best.pt"


def load_trained_network(path: Path | str, fingerprint: str | None = None, *, config: dict | None = None
                         ) -> tuple[RunConfig, torch.nn.Module, dict[str, Any]]:
    """The run config, the Q network (eval mode: noise and dropout off) and the raw payload of a
    trained checkpoint (a run folder or a ``best.pt``).

    Raises :class:`CheckpointError` naming the file for a missing, truncated or foreign file, a
    config the code cannot rebuild, weights that do not fit the network of the config, NaN or
    infinite weights (naming the parameter), or (given ``fingerprint``) a checkpoint written by a
    run with another configuration (given ``config`` too, the loading run's: naming the keys that differ).
    """
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    ckpt = checkpoint_path(path)
    data = load_checkpoint(ckpt, fingerprint, config=config)
    if "net" not in data or "config" not in data:
        raise CheckpointError(f"{ckpt} holds no trained network ('net' and 'config'); pass a run folder or its "
                              f"checkpoints/best.pt")
    try:
        # what training needed is no concern here; a key it predates: the value it ran with (STORED_DEFAULTS)
        run = validate(stored_config(data["config"]), resources=False)
    except ConfigError as exc:
        raise CheckpointError(f"{ckpt}: its config cannot be rebuilt by this code version: {exc}") from None
    if data.get("fingerprint") != config_fingerprint(to_dict(run)):
        raise CheckpointError(f"{ckpt}: its fingerprint does not match the config stored with it (edited or foreign file)")
    net = make_network(run, strategy=make_strategy(run.exploration))  # what acts on it: the evaluation's policy
    try:
        net.load_state_dict(data["net"])
    except RuntimeError as exc:
        first = str(exc).splitlines()[0]
        raise CheckpointError(f"{ckpt}: the network shape does not match its config ({first})") from None
    check_finite_weights(net, ckpt, "Q network")
    net.eval()  # noise and dropout off: the greedy policy of the mean network
    return run, net, data


def load_trained_predictor(run: RunConfig, data: dict[str, Any], path: Path | str = "checkpoint"
                           ) -> torch.nn.Module | None:
    """The planner's crowd predictor of a trained checkpoint's payload ``data`` (``None`` without
    planning; a ``const_vel`` predictor has no weights to load)."""
    from crowdrl.training.acting import make_predictor_of
    from crowdrl.training.facts import RunFacts

    predictor = make_predictor_of(run.planning, RunFacts.of(run))
    if predictor is None or not any(True for _ in predictor.parameters()):
        return predictor
    if "predictor" not in data:
        raise CheckpointError(f"{path}: planning.predictor=learned but the checkpoint holds no predictor weights")
    try:
        predictor.load_state_dict(data["predictor"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: the predictor's weights do not fit ({str(exc).splitlines()[0]})") from None
    check_finite_weights(predictor, path, "crowd predictor")
    return predictor.eval()
