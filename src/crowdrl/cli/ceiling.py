"""The ceiling of a stream of cases (Hydra entry point: ``crowdrl-ceiling``, ``python -m crowdrl.cli.ceiling`` or
``python experiments/ceiling.py`` in a checkout): each case labelled solved (with the fastest path found),
infeasible (every action sequence collides within ``horizon`` steps) or unknown, by the search of
:mod:`crowdrl.sim.oracle` that knows the humans' futures.

    python experiments/ceiling.py env=circle out=results/ceiling/circle.json
    python experiments/ceiling.py env=square cases=200 'widths=[64,512,2048]'
    python experiments/evaluate.py checkpoint=runs/<folder> eval.ceiling=results/ceiling/circle.json

Writes one JSON file (``out``; an existing one only with ``overwrite=true``) and prints the counts. Every
solved path is replayed through :class:`~crowdrl.envs.CrowdNavEnv` first (``replay=true``); a disagreement
writes nothing and exits 1. A bad key or value exits 2 naming it, with nothing written.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import NoReturn

from omegaconf import DictConfig

from crowdrl.cli import exit_with_error, hydra_command
from crowdrl.resources import config_dir

CONF_DIR = str(config_dir())


def fail(message: str) -> NoReturn:
    exit_with_error("ceiling", message)


def _register_schema() -> None:
    from hydra.core.config_store import ConfigStore

    from crowdrl.cli.schemas import CeilingConfig

    ConfigStore.instance().store(name="ceiling_schema", node=CeilingConfig)


_register_schema()


def allowed_hint(key: str = "") -> str:
    """The keys ceiling.py reads (its schema's), for its messages."""
    from crowdrl.cli.schemas import CeilingConfig
    from crowdrl.schema import allowed_keys

    return ", ".join(allowed_keys(CeilingConfig))


def default_out(scenario: str, split: str, seed: int, cases: int) -> str:
    return f"ceiling-{scenario}-{split}-seed{seed}-{cases}.json"


@hydra_command("ceiling", "ceiling", allowed=allowed_hint)
def main(cfg: DictConfig) -> dict:
    import torch

    from crowdrl.cli.schemas import CeilingConfig
    from crowdrl.evaluation.ceiling import check_settings, compute_ceiling, replay, write_ceiling
    from crowdrl.schema import SchemaError, read_typed
    from crowdrl.sim.oracle import check_searchable
    from crowdrl.training.config import RunConfig
    from crowdrl.training.config import crowd_config
    from crowdrl.training.validation import check_threads

    try:
        c = read_typed(CeilingConfig, cfg, reader="ceiling.py", allowed=allowed_hint())
    except SchemaError as exc:
        fail(str(exc))
    try:
        crowd = crowd_config(RunConfig(env=c.env))
    except ValueError as exc:
        fail(f"env.{exc}")
    try:
        check_searchable(crowd)
        check_settings(split=c.split, seed=c.seed, cases=c.cases, widths=tuple(c.widths), cell=c.cell,
                       horizon=c.horizon)
        check_threads(c.threads)
    except ValueError as exc:
        fail(str(exc).replace("robot_visible:", "env.robot_visible:").replace("width:", "widths:"))
    if isinstance(c.chunk, bool) or c.chunk < 1:
        fail(f"chunk: must be an integer >= 1, got {c.chunk!r}")
    out = Path(c.out or default_out(crowd.scenario, c.split, c.seed, c.cases))
    if out.exists() and not c.overwrite:
        fail(f"out: {out} exists; pass overwrite=true to replace it, or choose another out=")
    if out.exists() and not out.is_file():
        fail(f"out: {out} is not a file")
    if not out.parent.is_dir():
        fail(f"out: its folder {out.parent} does not exist")
    torch.set_num_threads(c.threads)

    from tqdm import tqdm

    with tqdm(total=c.cases, unit="case", desc=f"ceiling {crowd.scenario}") as bar:
        ceiling = compute_ceiling(crowd, split=c.split, seed=c.seed, cases=c.cases, widths=tuple(c.widths),
                                  cell=c.cell, horizon=c.horizon, chunk=c.chunk, progress=bar.update)
    if c.replay:
        wrong = replay(ceiling, dataclasses.replace(crowd, robot_kinematics="unicycle"))
        if wrong:
            exit_with_error("ceiling", f"{len(wrong)} solved paths disagree with CrowdNavEnv (nothing written): "
                                       f"{'; '.join(wrong[:3])}", code=1)
    write_ceiling(out, ceiling)
    n = ceiling.counts()
    by_width = ", ".join(f"width {w}: {k}" for w, k in ceiling.solved_by_width.items())
    print(f"{c.cases} {crowd.scenario} {c.split} cases, seed {c.seed}: solved {n['solved']}, infeasible "
          f"{n['infeasible']}, unknown {n['unknown']} (solved by {by_width}); mean time {ceiling.mean_time():.2f} s; "
          f"{ceiling.seconds:.0f} s" + (", every path replayed exactly" if c.replay else ""))
    print(f"wrote {out}")
    return ceiling.to_json()


if __name__ == "__main__":  # python -m crowdrl.cli.ceiling
    main()
