"""Build the API reference from the docstrings with pdoc: every public module of ``crowdrl`` (the command-line
modules and private ones left out), with signatures, into ``build/api`` (open ``build/api/index.html``).

    python experiments/api_docs.py [--out build/api]     # also: make api-docs
"""

from __future__ import annotations

import argparse
import pkgutil
import sys
import warnings
from pathlib import Path

import crowdrl


def public_modules() -> list[str]:
    """``crowdrl`` and every submodule whose dotted name has no part starting with ``_``, except ``crowdrl.cli``."""
    names = ["crowdrl"] + [m.name for m in pkgutil.walk_packages(crowdrl.__path__, "crowdrl.")]
    return [n for n in names if not any(p.startswith("_") for p in n.split(".")) and not n.startswith("crowdrl.cli")]


def build(out: Path) -> list[Path]:
    """The reference written to ``out``; the HTML pages."""
    import pdoc
    import pdoc.render

    pdoc.render.configure(docformat="restructuredtext", show_source=False)
    with warnings.catch_warnings():  # torch's and torchrl's forward references pdoc cannot resolve: shown as written
        warnings.filterwarnings("ignore", message="Error parsing type annotation")
        pdoc.pdoc(*public_modules(), output_directory=out)
    return sorted(out.rglob("*.html"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("build/api"))
    args = ap.parse_args(argv)
    pages = build(args.out)
    print(f"{len(pages)} pages in {args.out} (open {args.out / 'index.html'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
