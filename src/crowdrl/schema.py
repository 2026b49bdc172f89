"""A config tree read into its typed schema (a dataclass), every refusal naming the key.

The Hydra commands compose their config onto a schema registered in Hydra's ConfigStore (``train``:
:class:`crowdrl.training.config.RunConfig`; ``evaluate``, ``export``: :mod:`crowdrl.cli.schemas`;
``reproduce``: :class:`crowdrl.reproduction.config.ReproduceConfig`), so Hydra itself refuses an
unknown key and a value of the wrong type. A key added with ``+key=value`` gets through Hydra's
composition; :func:`read_typed` reads the composed tree into the schema and refuses it, naming it.

A bool key takes ``true`` or ``false`` only: OmegaConf would turn any integer into a bool (``2`` into
``true``), so :func:`check_bools` (a tree read into its schema) and :func:`check_bool_overrides` (the
command line's overrides, which Hydra has already converted) refuse anything else, naming the key.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

T = TypeVar("T")


class SchemaError(ValueError):
    """A key the schema lacks, or a value of the wrong type for it; ``key`` is its dotted name."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


def allowed_keys(schema: type, prefix: str = "") -> list[str]:
    """The dotted names of ``schema``'s fields (those of a nested dataclass expanded)."""
    out: list[str] = []
    for f in dataclasses.fields(schema):
        nested = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        if isinstance(nested, type) and dataclasses.is_dataclass(nested):
            out += allowed_keys(nested, f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


def check_bools(typed: Any, raw: Any, prefix: str = "") -> None:
    """Raise :class:`SchemaError` ``"<key>: must be true or false, got <value>"`` for the first key
    whose value in ``typed`` (a dataclass instance read from ``raw``) is a bool but whose value in
    ``raw`` (the mapping it was read from) is not: one OmegaConf converted (``2``, ``"yes"``)."""
    if not dataclasses.is_dataclass(typed) or not isinstance(raw, Mapping):
        return
    for f in dataclasses.fields(typed):
        if f.name not in raw:
            continue
        value, given, key = getattr(typed, f.name), raw[f.name], f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            check_bools(value, given, f"{key}.")
        elif isinstance(value, bool) and not isinstance(given, bool):
            raise SchemaError(key, f"must be true or false, got {given!r}")


def check_bool_overrides(cfg: DictConfig, overrides: list[str]) -> None:
    """Raise :class:`SchemaError` naming the key of the first command-line override (Hydra's syntax,
    ``train.q_layer_norm=2``) that is not ``true`` or ``false`` but that the composed typed ``cfg``
    holds as a bool: Hydra converted it (``2``, ``yes``, ``'true'``). ``hydra.*``, deletions and
    interpolations are left to Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    for override in OverridesParser.create().parse_overrides(list(overrides)):
        key = override.key_or_group
        if override.is_delete() or key == "hydra" or key.startswith("hydra.") or "@" in key:
            continue
        value = override.value()
        if isinstance(value, bool) or (isinstance(value, str) and "${" in value):
            continue
        try:
            composed = OmegaConf.select(cfg, key, default=None, throw_on_missing=False)
        except OmegaConfBaseException:
            continue
        if isinstance(composed, bool):
            raise SchemaError(key, f"must be true or false, got {value!r}")


def read_typed(schema: type[T], cfg: DictConfig | Mapping[str, Any], *, reader: str, allowed: str | None = None) -> T:
    """``cfg`` (resolved) merged onto ``schema``'s defaults, as a ``schema`` instance.

    A key ``schema`` lacks raises :class:`SchemaError` ``"<key>: not read by <reader> (unknown key);
    allowed: <allowed>"`` (default: the schema's dotted keys, :func:`allowed_keys`); a value of the
    wrong type or a missing required one ``"<key>: <OmegaConf's reason>"``.

    Examples:
        >>> from dataclasses import dataclass
        >>> @dataclass
        ... class Settings:
        ...     episodes: int = 10
        ...     name: str = "orca"
        >>> read_typed(Settings, {"episodes": 3}, reader="demo.py")
        Settings(episodes=3, name='orca')
        >>> read_typed(Settings, {"episods": 3}, reader="demo.py")
        Traceback (most recent call last):
            ...
        crowdrl.schema.SchemaError: episods: not read by demo.py (unknown key); allowed: episodes, name
        >>> read_typed(Settings, {"episodes": "abc"}, reader="demo.py")
        Traceback (most recent call last):
            ...
        crowdrl.schema.SchemaError: episodes: Value 'abc' of type 'str' could not be converted to Integer
    """
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    try:
        typed = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), cfg))
    except OmegaConfBaseException as exc:
        key = str(getattr(exc, "full_key", "") or "")
        if isinstance(exc, ConfigKeyError):
            raise SchemaError(key, f"not read by {reader} (unknown key); "
                                   f"allowed: {allowed or ', '.join(allowed_keys(schema))}") from None
        raise SchemaError(key, str(exc).splitlines()[0]) from None
    check_bools(typed, cfg)
    return typed  # type: ignore[return-value]


__all__ = ["SchemaError", "allowed_keys", "check_bool_overrides", "check_bools", "read_typed"]
