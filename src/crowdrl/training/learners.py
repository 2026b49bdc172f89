"""The learners of ``conf/learner/`` and which one each budget preset trains with.

``recommended`` (the default): counterfactual experience and Polyak target updates; ``paper``: upstream
SG-D3QN's top-5 second update with hard target copies (``preset=paper`` selects it); ``plain``: neither,
what a stored config without the keys ran with. ``train.py learner=<name>`` picks one; its keys can then be set one by one.

>>> learner_of_preset("paper"), learner_of_preset("demo")
('paper', 'recommended')
>>> learner_settings("plain")
{'counterfactual': {'mode': 'off'}, 'target_tau': 1.0}
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf

from crowdrl.resources import config_dir

DEFAULT_LEARNER = "recommended"  # conf/config.yaml's defaults list


def learners() -> tuple[str, ...]:
    """The learners ``conf/learner/`` holds."""
    return tuple(sorted(p.stem for p in (config_dir() / "learner").glob("*.yaml")))


def learner_of_preset(preset: str) -> str:
    """The learner ``conf/preset/<preset>.yaml`` selects (``override /learner: ...`` in its defaults
    list), else :data:`DEFAULT_LEARNER`."""
    node = OmegaConf.to_container(OmegaConf.load(config_dir() / "preset" / f"{preset}.yaml"))
    for entry in node.get("defaults", []):
        if isinstance(entry, dict):
            for key, value in entry.items():
                if key.replace("override", "").strip().lstrip("/") == "learner":
                    return str(value)
    return DEFAULT_LEARNER


def learner_settings(name: str) -> dict[str, Any]:
    """The ``train`` keys ``conf/learner/<name>.yaml`` sets (``counterfactual``, ``target_tau``)."""
    if name not in learners():
        raise ValueError(f"learner: unknown {name!r}; allowed: {', '.join(learners())}")
    return OmegaConf.to_container(OmegaConf.load(config_dir() / "learner" / f"{name}.yaml"))["train"]


__all__ = ["DEFAULT_LEARNER", "learner_of_preset", "learner_settings", "learners"]
