"""Evaluate a trained checkpoint or a baseline on fixed test cases (Hydra entry point: ``crowdrl-evaluate``,
``python -m crowdrl.cli.evaluate`` or ``python experiments/evaluate.py`` in a checkout).

    python experiments/evaluate.py checkpoint=runs/<folder>                  # its scenario, 1000 cases
    python experiments/evaluate.py checkpoint=runs/<folder> env=square       # zero-shot on square
    python experiments/evaluate.py checkpoint=runs/<folder> eval.human_model=social_force eval.robot_visible=true
    python experiments/evaluate.py policy=orca env=square eval.seed=1 eval.episodes=200
    python experiments/evaluate.py policy=orca hydra.run.dir=results/orca    # choose the output folder

Prints a Markdown table and writes ``eval.json`` / ``eval.csv`` (and a PNG and GIF of
``eval.record_episode``) into its Hydra run folder, whose path it prints. The same cases give the
same numbers whatever ``eval.batch``.
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from crowdrl.cli import exit_with_error, hydra_command
from crowdrl.resources import config_dir

CONF_DIR = str(config_dir())


def _register_resolvers() -> None:
    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()  # ${crowdrl_uid:} in the default eval folder's name


_register_resolvers()


def check_keys(c: dict, overrides: list[str]) -> None:
    """Refuse keys that nothing reads, naming them: a misspelt key Hydra lets through when added with
    ``+`` (``+eval.episods=5``), a group of train.py (``+encoder=sarl``), an ``env.*`` key other than
    ``env.scenario`` (the crowd size is ``eval.num_humans``). The known keys are those of
    ``conf/evaluate.yaml`` and of the ``conf/env/`` files."""
    from crowdrl.training.config import ConfigError
    from crowdrl.training.validation import unknown_keys

    known = OmegaConf.to_container(OmegaConf.load(Path(CONF_DIR) / "evaluate.yaml"))
    known.pop("defaults", None)
    known["env"] = {k: None for f in sorted((Path(CONF_DIR) / "env").glob("*.yaml"))
                    for k in OmegaConf.to_container(OmegaConf.load(f))}
    bad = unknown_keys(c, known)
    bad += [key for key in (item.split("=", 1)[0].lstrip("+~") for item in overrides)
            if key.startswith("env.") and key != "env.scenario"]
    if bad:
        raise ConfigError(f"{', '.join(bad)}: not read by evaluate.py (unknown key); allowed: checkpoint, policy, "
                          f"{', '.join(f'eval.{k}' for k in known['eval'])}, threads, device, env=<scenario> "
                          f"(the crowd size is eval.num_humans, the humans' model eval.human_model, whether "
                          f"they see the robot eval.robot_visible)")


@hydra_command("evaluate", "evaluate")
def main(cfg: DictConfig) -> dict:
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        return run_evaluation(out, cfg)
    except (KeyboardInterrupt, OSError):  # stopped, or a full / read-only disk: one_line_errors reports it
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(out)  # the eval folder Hydra made, only while still empty (atomic writes leave no part)
        raise


def run_evaluation(out: Path, cfg: DictConfig) -> dict:
    """Evaluate what ``cfg`` names into the folder ``out`` (Hydra's run folder); the record."""
    import torch

    from crowdrl.evaluation.report import markdown_table, write_records
    from crowdrl.training import CheckpointError, ConfigError
    from crowdrl.training.validation import check_device, check_threads
    from crowdrl.training.pipeline import evaluate_spec

    c = OmegaConf.to_container(cfg, resolve=True)
    try:
        check_keys(c, list(HydraConfig.get().overrides.task))
        check_device(str(c["device"]))
        check_threads(c["threads"])
        torch.set_num_threads(c["threads"])
        scenario = (c.get("env") or {}).get("scenario")  # env=<name> selects conf/env/<name>.yaml
        e = c["eval"]
        record, traj = evaluate_spec(checkpoint=c["checkpoint"], policy=c["policy"], scenario=scenario, seed=e["seed"],
                                     episodes=e["episodes"], num_humans=e["num_humans"], batch=e["batch"],
                                     record_episode=e["record_episode"], device=c["device"],
                                     human_model=e["human_model"], robot_visible=e["robot_visible"])
    except (ValueError, ConfigError, CheckpointError) as exc:
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(out)  # only the folder Hydra made for this evaluation, and only while empty
        exit_with_error("evaluate", f"checkpoint: {exc}" if isinstance(exc, CheckpointError) else str(exc))
    write_records(out, [record])
    if traj is not None:
        from crowdrl.viz import animate_trajectory, plot_trajectory

        name = f"{record['scenario']}_case{e['record_episode']}"
        plot_trajectory(traj, out / f"{name}.png", title=f"{record['policy']}, {record['scenario']} test case "
                                                          f"{e['record_episode']}")
        animate_trajectory(traj, out / f"{name}.gif")
    print(f"{record['episodes']} {record['scenario']} test cases, test seed {record['seed']}")
    print(markdown_table([record]))
    print(f"eval folder: {out.resolve()}")
    return record


if __name__ == "__main__":  # python -m crowdrl.cli.evaluate
    main()
