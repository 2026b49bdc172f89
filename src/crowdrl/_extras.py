"""The error for an optional dependency that is not installed: it names the extra to install."""

from __future__ import annotations


def missing(module: str, extra: str, purpose: str) -> ImportError:
    """``ImportError`` saying that ``purpose`` needs ``module``, from crowdrl's ``extra``."""
    return ImportError(f"{purpose} needs {module}, which is not installed: it comes with crowdrl's "
                       f"{extra!r} extra, pip install 'crowdrl[{extra}]'")
