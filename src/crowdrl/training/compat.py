"""Stored configs of earlier runs (a run folder's ``config.yaml``, a checkpoint's config): a key
they predate whose default has changed since takes the value they ran with."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from crowdrl.training.config import COUNTERFACTUAL_OFF, LEVERS_OFF, RunConfig

# Keys whose schema default changed after run folders were recorded, at the value those folders ran
# with: a stored config (a run folder's config.yaml, a checkpoint's config) that lacks one ran with
# this value, not with today's default. planning.enabled: off before planning was the default (the
# schema's default was off until one set of defaults); train.compile_acting: off in the schema before;
# train.counterfactual.mode and train.target_tau: off and hard copies (the plain learner) before the
# recommended learner became the default (issue 50).
STORED_DEFAULTS = {"planning": {"enabled": False},
                   "train": {"compile_acting": False, "counterfactual": {"mode": COUNTERFACTUAL_OFF["mode"]},
                             "target_tau": LEVERS_OFF["target_tau"]}}


def stored_config(cfg: DictConfig | dict) -> dict:
    """A stored config with :data:`STORED_DEFAULTS` filled in where it lacks them: what that run ran with.

    >>> stored_config({"seed": 1})["planning"]
    {'enabled': False}
    >>> stored_config({"planning": {"enabled": True}})["planning"]
    {'enabled': True}
    >>> stored_config({"train": {"counterfactual": {"k": 3}}})["train"]["counterfactual"]
    {'k': 3, 'mode': 'off'}
    """
    def fill(node: object, defaults: dict) -> dict:
        node = dict(node) if isinstance(node, dict) else {}
        for key, value in defaults.items():
            node[key] = fill(node.get(key), value) if isinstance(value, dict) else node.get(key, value)
        return node

    out = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    for group, keys in STORED_DEFAULTS.items():
        out[group] = fill(out.get(group), keys)
    return out


def resume_conflicts(current: DictConfig, saved: DictConfig, overrides: list[str]) -> list[str]:
    """The command-line ``overrides`` that disagree with a run folder's ``saved`` config.

    ``current`` is the config Hydra composed with those overrides. A key the saved file lacks (it
    predates the key) takes the schema's default, which is what ``validate(saved)`` runs with, except
    for :data:`STORED_DEFAULTS` (the value it ran with: :func:`stored_config`).
    ``resume`` and ``hydra.*`` are not compared; a config group (``env=...``) compares its content.

    >>> from omegaconf import OmegaConf
    >>> resume_conflicts(OmegaConf.create({"seed": 0}), OmegaConf.create({"seed": 1}), ["seed=0"])
    ['seed=0 (the run has seed=1)']
    """
    def complete(cfg: DictConfig) -> DictConfig:  # every schema key, the file's values over the defaults
        return OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.to_container(cfg, resolve=True))

    now, then = complete(current), complete(OmegaConf.create(stored_config(saved)))
    conflicts = []
    for item in overrides:
        key = item.split("=", 1)[0].lstrip("+~")
        if key == "resume" or key.startswith("hydra"):
            continue
        had = OmegaConf.select(then, key, default=None)
        same = OmegaConf.select(now, key, default=None) == had
        if not same:
            conflicts.append(f"{item} (the run has {key}={had})")
    return conflicts
