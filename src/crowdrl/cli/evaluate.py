"""Evaluate a trained checkpoint or a baseline on fixed test cases (Hydra entry point: ``crowdrl-evaluate``,
``python -m crowdrl.cli.evaluate`` or ``python experiments/evaluate.py`` in a checkout).

    python experiments/evaluate.py checkpoint=runs/<folder>                  # its scenario, 1000 cases
    python experiments/evaluate.py checkpoint=runs/<folder> env=square       # zero-shot on square
    python experiments/evaluate.py checkpoint=runs/<folder> eval.human_model=social_force eval.robot_visible=true
    python experiments/evaluate.py checkpoint=runs/<folder> eval.human_model=mixed \
        eval.social_force_share=0.3 eval.linear_share=0.3
    python experiments/evaluate.py policy=orca env=square eval.seed=1 eval.episodes=200
    python experiments/evaluate.py policy=orca hydra.run.dir=results/orca    # choose the output folder
    python experiments/evaluate.py checkpoint=runs/<folder> eval.ceiling=results/ceiling/circle.json  # gap to it
    python experiments/evaluate.py checkpoint=runs/<folder> eval.planning_depth=2   # act with a deeper planner
    python experiments/evaluate.py checkpoint=runs/<folder> eval.planning_depth=0   # planning off: greedy on Q
    python experiments/evaluate.py checkpoint=policy.onnx env=square   # an exported model, through onnxruntime

Prints a Markdown table and writes ``eval.json`` / ``eval.csv`` (and a PNG and GIF of
``eval.record_episode``) into its Hydra run folder, whose path it prints: a new or empty folder
(one that holds anything, a training run's folder among them, is refused). The same cases give the
same numbers whatever ``eval.batch``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from crowdrl.cli import exit_with_error, hydra_command
from crowdrl.resources import config_dir

if TYPE_CHECKING:
    from crowdrl.cli.schemas import EvaluateConfig

CONF_DIR = str(config_dir())


def _register_resolvers() -> None:
    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()  # ${crowdrl_uid:} in the default eval folder's name


_register_resolvers()


def _register_schema() -> None:
    """The typed schema of ``conf/evaluate.yaml`` (its defaults list's ``evaluate_schema``): Hydra
    refuses an unknown key or a value of the wrong type, naming it."""
    from hydra.core.config_store import ConfigStore

    from crowdrl.cli.schemas import EvaluateConfig

    ConfigStore.instance().store(name="evaluate_schema", node=EvaluateConfig)


_register_schema()


def allowed_hint(key: str = "") -> str:
    """The keys evaluate.py reads, for its messages: its schema's, ``env`` as ``env=<scenario>``."""
    from crowdrl.cli.schemas import EvaluateConfig
    from crowdrl.schema import allowed_keys

    keys = [k for k in allowed_keys(EvaluateConfig) if not k.startswith("env.")]
    return (f"{', '.join(keys)}, env=<scenario> (the crowd size is eval.num_humans, the humans' model "
            f"eval.human_model with eval.social_force_share / eval.linear_share for a mixed crowd, whether they "
            f"see the robot eval.robot_visible)")


def read_settings(cfg: DictConfig, overrides: list[str]) -> EvaluateConfig:
    """``cfg`` as an :class:`~crowdrl.cli.schemas.EvaluateConfig`. Refused, naming the key: one the
    schema lacks, added with ``+`` (``+eval.episods=5``, ``+encoder=sarl``: Hydra refuses the others),
    and an override of an ``env.*`` key other than ``env.scenario``: ``env=<scenario>`` selects
    ``conf/env/<scenario>.yaml``, of which only the scenario is read (the crowd is ``eval.*``)."""
    from crowdrl.cli.schemas import EvaluateConfig
    from crowdrl.schema import read_typed

    bad = [key for key in (item.split("=", 1)[0].lstrip("+~") for item in overrides)
           if key.startswith("env.") and key != "env.scenario"]
    if bad:
        raise ValueError(f"{', '.join(bad)}: not read by evaluate.py (unknown key); allowed: {allowed_hint()}")
    return read_typed(EvaluateConfig, cfg, reader="evaluate.py", allowed=allowed_hint())


@hydra_command("evaluate", "evaluate", allowed=allowed_hint)
def main(cfg: DictConfig) -> dict:
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        return run_evaluation(out, cfg)
    except (KeyboardInterrupt, OSError):  # stopped, or a full / read-only disk: one_line_errors reports it
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(out)  # the eval folder Hydra made, only while still empty (atomic writes leave no part)
        raise


def check_eval_folder(out: Path) -> None:
    """Refuse (``ValueError`` naming ``hydra.run.dir``) an eval folder that is a file or holds anything:
    evaluate.py writes only into the folder Hydra made for it or an empty one, never over a record
    (a training run's own ``eval.json``) it did not write in this call."""
    from crowdrl.training.run_folder import RunFolderRefused, check_folder

    try:
        check_folder(out)
    except RunFolderRefused as exc:
        raise ValueError(f"hydra.run.dir: {exc}; evaluate.py writes only into a new or empty folder") from None


def run_evaluation(out: Path, cfg: DictConfig) -> dict:
    """Evaluate what ``cfg`` names into the folder ``out`` (Hydra's run folder); the record."""
    import torch

    from crowdrl.evaluation.report import markdown_table, write_records
    from crowdrl.training import CheckpointError, ConfigError
    from crowdrl.training.validation import check_device, check_threads
    from crowdrl.agents import evaluate_spec

    try:
        c = read_settings(cfg, list(HydraConfig.get().overrides.task))
        check_device(c.device)
        check_threads(c.threads)
        check_eval_folder(out)
        torch.set_num_threads(c.threads)
        scenario = c.env.scenario  # env=<name> selects conf/env/<name>.yaml (None: the checkpoint's)
        e = c.eval
        record, traj = evaluate_spec(checkpoint=c.checkpoint, policy=c.policy, scenario=scenario, seed=e.seed,
                                     episodes=e.episodes, num_humans=e.num_humans, batch=e.batch,
                                     record_episode=e.record_episode, device=c.device,
                                     human_model=e.human_model, robot_visible=e.robot_visible,
                                     social_force_share=e.social_force_share, linear_share=e.linear_share,
                                     ceiling=e.ceiling, planning={"depth": e.planning_depth, "width": e.planning_width,
                                                                  "safety_horizon": e.planning_safety_horizon,
                                                                  "progress_bias": e.planning_progress_bias})
    except (ValueError, ConfigError, CheckpointError) as exc:
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(out)  # only the folder Hydra made for this evaluation, and only while empty
        exit_with_error("evaluate", f"checkpoint: {exc}" if isinstance(exc, CheckpointError) else str(exc))
    write_records(out, [record])
    if traj is not None:
        from crowdrl.viz import animate_trajectory, plot_trajectory

        name = f"{record['scenario']}_case{e.record_episode}"
        plot_trajectory(traj, out / f"{name}.png", title=f"{record['policy']}, {record['scenario']} test case "
                                                          f"{e.record_episode}")
        animate_trajectory(traj, out / f"{name}.gif")
    print(f"{record['episodes']} {record['scenario']} test cases, test seed {record['seed']}")
    print(markdown_table([record]))
    if "avoidable_failures" in record:
        print(f"ceiling {record['ceiling_success']:.3f}: avoidable failures {record['avoidable_failures']}, unavoidable "
              f"{record['unavoidable_failures']}, unknown {record['unknown_failures']}; time over the ceiling "
              f"{record['time_over_ceiling']:.2f} s on the {record['both_solved']} cases both solve")
    print(f"eval folder: {out.resolve()}")
    return record


if __name__ == "__main__":  # python -m crowdrl.cli.evaluate
    main()
