"""Train a crowd-navigation agent (Hydra entry point: ``crowdrl-train``, ``python -m crowdrl.cli.train``,
or ``python experiments/train.py`` in a checkout; the configs are crowdrl's own, :func:`crowdrl.resources.config_dir`).

    python experiments/train.py                                # demo preset, SG-D3QN, ε-greedy, circle, the recommended learner
    python experiments/train.py learner=plain                  # without counterfactual experience, hard target copies
    python experiments/train.py preset=paper seed=1            # the paper's budget and learner
    python experiments/train.py -m preset=smoke seed=0,1       # multirun
    python experiments/train.py resume=runs/<folder>           # continue a killed run
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from crowdrl.cli import command, exit_with_error, folder_error_line, hydra_command
from crowdrl.resources import config_dir

CONF_DIR = str(config_dir())


def _register_resolvers() -> None:
    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()


_register_resolvers()


def _register_schema() -> None:
    """Make every key of the typed schema overridable (``train.save_buffer=true``) and type-checked."""
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.config import RunConfig

    ConfigStore.instance().store(name="run_schema", node=RunConfig)


_register_schema()


def allowed_hint(key: str = "") -> str:
    """The run config's keys beside a refused ``key`` (its section's), for the unknown-key message."""
    from crowdrl.training.validation import keys_beside

    return ", ".join(keys_beside(key)) or "the keys of conf/config.yaml (docs/training.md)"


@hydra_command("train", "config", allowed=allowed_hint)
def main(cfg: DictConfig) -> float:
    from crowdrl.training import CheckpointError, ConfigError, run_training, validate
    from crowdrl.training.pipeline import completed_summary
    from crowdrl.training.run_folder import RunFolderRefused, discard_new_folders
    from crowdrl.evaluation.metrics import seconds
    from crowdrl.training.trainer import NonFiniteError

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        run = validate(cfg)
        if run.resume:
            cfg, run = resumed_config(cfg, Path(run.resume), HydraConfig.get().overrides.task)
    except ConfigError as exc:
        discard_new_folders(out_dir)  # only a folder this run created, and only while empty
        exit_with_error("train", f"invalid configuration: {exc}")
    run_dir = Path(run.resume) if run.resume else out_dir
    if run.resume:
        discard_new_folders(out_dir)
    status = run_dir / "status.json"
    complete_status = status.read_bytes() if completed_summary(run_dir) is not None else None
    print(f"run folder: {run_dir.resolve()}", flush=True)
    try:  # config.yaml, .hydra/ and train.log: written only once every check has passed, under the lock
        summary = run_training(run, run_dir, prepare=None if run.resume else lambda: _start_run_folder(run_dir, cfg))
    except (CheckpointError, RunFolderRefused) as exc:  # refused before anything in the folder changed
        if not run.resume:
            discard_new_folders(out_dir)
        exit_with_error("train", f"cannot run in {run_dir}: {exc}")
    except NonFiniteError as exc:  # status.json says "failed" and why; no eval.json is written
        exit_with_error("train", f"training failed: {exc} (run folder: {run_dir.resolve()})", code=1)
    except KeyboardInterrupt as exc:  # SIGTERM/SIGINT: checkpointed, status "interrupted"
        exit_with_error("train", f"interrupted ({exc}); resume with: {command('train')} resume={run_dir}", code=130)
    except OSError as exc:  # a full disk, a read-only or forbidden folder: the last complete checkpoint stays
        line = folder_error_line(exc)
        if line is None:
            raise
        if not run.resume:
            discard_new_folders(out_dir)
        exit_with_error("train", f"{line} (run folder {run_dir}; its checkpoints/last.pt, if any, is the last complete "
                                 f"one: resume with {command('train')} resume={run_dir})")
    m = summary["test"]["metrics"]
    if complete_status is not None and status.read_bytes() == complete_status:  # run_training returned at once
        print(f"run folder {run_dir.resolve()} holds a completed run: nothing to train or test, nothing changed")
    elif run.logger.render:
        render(run, run_dir)
    print(f"run folder: {run_dir.resolve()}")
    print(f"test ({m['episodes']} cases): success {m['success_rate']:.3f}  collision {m['collision_rate']:.3f}  "
          f"nav time {seconds(m['navigation_time'])}  return {m['average_return']:.4f}")
    return float(m["success_rate"])


def render(run, run_dir: Path) -> None:
    """``learning_curves.png`` and test case 0's PNG and GIF, drawn from the run folder's files (``logger.render``)."""
    from crowdrl.viz import render_run_folder

    render_run_folder(run_dir, title=f"{run.encoder.name} + {run.exploration.name}, {run.env.scenario}, seed {run.seed}")


def _start_run_folder(run_dir: Path, cfg: DictConfig) -> None:
    """The files of a fresh run: ``config.yaml``, Hydra's ``.hydra/`` (what ``hydra.output_subdir``
    would have written before the checks) and the ``train.log`` handler of the root logger."""
    import logging

    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    hydra_dir = run_dir / ".hydra"
    hydra_dir.mkdir(exist_ok=True)
    hydra_cfg = HydraConfig.get()
    (hydra_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    (hydra_dir / "hydra.yaml").write_text(OmegaConf.to_yaml(HydraConfig.instance().cfg))
    (hydra_dir / "overrides.yaml").write_text(OmegaConf.to_yaml(hydra_cfg.overrides.task))
    handler = logging.FileHandler(run_dir / f"{hydra_cfg.job.name}.log")
    handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
    logging.getLogger().addHandler(handler)


def resumed_config(cfg: DictConfig, run_dir: Path, overrides: list[str]):
    """The run folder's own ``config.yaml`` (with ``resume`` set). Command-line overrides other than
    ``resume`` and ``hydra.*`` must agree with it; any that do not are refused, by name."""
    from crowdrl.training import ConfigError, validate
    from crowdrl.training.compat import resume_conflicts, stored_config

    if not (run_dir / "checkpoints" / "last.pt").is_file():
        raise ConfigError(f"resume={run_dir}: no checkpoints/last.pt there")
    if not (run_dir / "config.yaml").is_file():
        raise ConfigError(f"resume={run_dir}: no config.yaml there (not a run folder of train.py)")
    try:
        saved = OmegaConf.load(run_dir / "config.yaml")
        conflicts = resume_conflicts(cfg, saved, overrides)
    except Exception as exc:  # YAML that does not parse, a key or _target_ the schema lacks, a group of the wrong type
        from crowdrl.cli import config_error_line

        detail = config_error_line(exc) or " ".join(str(exc).split())[:300]
        raise ConfigError(f"resume={run_dir}: its config.yaml is not a run config train.py can read ({detail}); "
                          f"restore the file train.py wrote, or start a new run") from None
    if conflicts:
        raise ConfigError(f"resume={run_dir}: a resumed run keeps its own config.yaml; refused override(s): "
                          + "; ".join(conflicts))
    # a key the folder predates whose default has changed since (planning.enabled, train.compile_acting):
    # the value the folder ran with (STORED_DEFAULTS), so an old run without planning never resumes planning
    saved = OmegaConf.create(stored_config(saved))
    saved.resume = str(run_dir)
    return saved, validate(saved)


if __name__ == "__main__":  # python -m crowdrl.cli.train
    main()
