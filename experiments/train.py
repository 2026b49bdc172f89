"""Train a crowd-navigation agent (Hydra entry point).

    python experiments/train.py                                # demo preset, SG-D3QN, ε-greedy, circle
    python experiments/train.py preset=paper seed=1
    python experiments/train.py -m preset=smoke seed=0,1       # multirun
    python experiments/train.py resume=runs/<folder>           # continue a killed run
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

os.environ.setdefault("WANDB_MODE", "offline")

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def _register_schema() -> None:
    """Make every key of the typed schema overridable (``train.save_buffer=true``) and type-checked."""
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.config import RunConfig

    ConfigStore.instance().store(name="run_schema", node=RunConfig)


_register_schema()


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    from crowdrl.training import ConfigError, run_training, validate

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        run = validate(cfg)
    except ConfigError as exc:
        _discard_empty_run_dir(out_dir)
        print(f"invalid configuration: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    run_dir = Path(run.resume) if run.resume else out_dir
    if run.resume:
        if not (run_dir / "checkpoints" / "last.pt").is_file():
            _discard_empty_run_dir(out_dir)
            print(f"resume={run.resume}: no checkpoints/last.pt there", file=sys.stderr)
            raise SystemExit(2)
        _discard_empty_run_dir(out_dir)
    else:
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    from crowdrl.training.trainer import NonFiniteError

    try:
        summary = run_training(run, run_dir)
    except NonFiniteError as exc:  # status.json says "failed" and why; no eval.json is written
        print(f"training failed: {exc} (run folder: {run_dir.resolve()})", file=sys.stderr)
        raise SystemExit(1) from None
    m = summary["test"]["metrics"]
    print(f"run folder: {run_dir.resolve()}")
    print(f"test ({m['episodes']} cases): success {m['success_rate']:.3f}  collision {m['collision_rate']:.3f}  "
          f"nav time {m['navigation_time']:.2f} s  return {m['average_return']:.4f}")
    return float(m["success_rate"])


def _discard_empty_run_dir(path: Path) -> None:
    """Remove a run folder Hydra created if it holds nothing but Hydra's own files."""
    if path.is_dir() and all(p.name in (".hydra", "train.log") for p in path.iterdir()):
        shutil.rmtree(path, ignore_errors=True)


if __name__ == "__main__":
    main()
