"""The OmegaConf resolvers that ``conf/`` uses."""

from __future__ import annotations

from omegaconf import OmegaConf


def run_uid() -> str:
    """Six random hex digits: the unique part of a default run folder's name."""
    import secrets

    return secrets.token_hex(3)


def register_resolvers() -> None:
    """``${crowdrl_uid:}`` for ``conf/``: :func:`run_uid`, the same for every use within one
    config (run folder names: two runs started in the same second never share a folder)."""
    if not OmegaConf.has_resolver("crowdrl_uid"):
        OmegaConf.register_new_resolver("crowdrl_uid", run_uid, use_cache=True)
