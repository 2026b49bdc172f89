"""A config tree read into its typed schema (a dataclass), every refusal naming the key.

The Hydra commands compose their config onto a schema registered in Hydra's ConfigStore (``train``:
:class:`crowdrl.training.config.RunConfig`; ``evaluate``, ``export``: :mod:`crowdrl.cli.schemas`;
``reproduce``: :class:`crowdrl.reproduction.config.ReproduceConfig`), so Hydra itself refuses an
unknown key and a value of the wrong type. A key added with ``+key=value`` gets through Hydra's
composition; :func:`read_typed` reads the composed tree into the schema and refuses it, naming it.
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
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), cfg))  # type: ignore[return-value]
    except OmegaConfBaseException as exc:
        key = str(getattr(exc, "full_key", "") or "")
        if isinstance(exc, ConfigKeyError):
            raise SchemaError(key, f"not read by {reader} (unknown key); "
                                   f"allowed: {allowed or ', '.join(allowed_keys(schema))}") from None
        raise SchemaError(key, str(exc).splitlines()[0]) from None


__all__ = ["SchemaError", "allowed_keys", "read_typed"]
