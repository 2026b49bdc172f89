"""One set of defaults: the typed schema (``RunConfig``) and ``conf/config.yaml`` composed with no
overrides (``preset=demo``) train the same thing, key by key."""

from pathlib import Path

import pytest

from crowdrl.training.config import RunConfig

ROOT = Path(__file__).resolve().parents[1]


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _compose(*overrides: str) -> dict:
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from crowdrl.training.resolvers import register_resolvers

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    register_resolvers()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    out = OmegaConf.to_container(cfg, resolve=False)
    out.pop("hydra", None)  # not in the schema
    return out


def test_conf_composed_with_no_overrides_equals_the_schema_defaults_key_by_key():
    from omegaconf import OmegaConf

    conf = _flat(_compose())
    schema = _flat(OmegaConf.to_container(OmegaConf.structured(RunConfig)))
    assert sorted(conf) == sorted(schema)
    assert {k: conf[k] for k in conf if conf[k] != schema[k]} == {}
    # the algorithm: SG-D3QN plans, as upstream; the budget: the demo's; acting eager in both (speed only)
    run = RunConfig()
    assert run.preset == "demo" and run.planning.enabled and not run.train.compile_acting


@pytest.mark.parametrize("preset", ["paper", "episodes"])
def test_paper_presets_keep_their_budget_and_each_variants_schedule(preset):
    anneal = {"egreedy": 200_000, "noisy": 200_000, "dropout": 350_000, "icm": 200_000, "re3": 200_000,
              "icm_published": 200_000, "re3_published": 200_000}
    for group, frames in anneal.items():
        cfg = _compose(f"preset={preset}", f"exploration={group}")
        assert cfg["preset"] == preset and cfg["exploration"]["anneal_frames"] == frames, group
        assert cfg["train"]["total_frames"] == 500_000 and cfg["train"]["compile_acting"] is True
        assert cfg["planning"]["enabled"] is True
    paper = _compose("preset=paper")["train"]
    assert (paper["num_envs"], paper["updates_per_frame"], paper["target_update_frames"],
            paper["val_every_frames"], paper["checkpoint_every_frames"]) == (16, 1.0, 25_000, 25_000, 25_000)


def test_the_generalists_budget_is_the_episodes_preset_at_twice_the_frames_weighted_towards_the_walls():
    """``preset=episodes2x`` (the budget of ``reproduce.py train_scenario=mix``): every key as ``preset=episodes``
    but ``train.total_frames`` (1M for five scenarios in one network, where a specialist trains 500k on one), and
    ``env=mix`` gives each wall scenario twice an open one's rows."""
    one, two = (_compose(f"preset={p}", "env=mix") for p in ("episodes", "episodes2x"))
    assert two["train"]["total_frames"] == 2 * one["train"]["total_frames"] == 1_000_000
    assert {**two, "preset": "episodes", "train": {**two["train"], "total_frames": 500_000}} == one
    assert one["env"]["mix"] == {"circle": 1, "square": 1, "corridor": 2, "doorway": 2, "room": 2}


def test_a_stored_config_that_predates_a_changed_default_keeps_what_it_ran_with():
    from omegaconf import OmegaConf

    from crowdrl.training.compat import STORED_DEFAULTS, stored_config

    from crowdrl.training.validation import validate

    saved = OmegaConf.to_container(OmegaConf.structured(RunConfig()))
    del saved["planning"]  # written before the planning key existed: trained without planning
    del saved["train"]["compile_acting"]
    del saved["train"]["target_tau"]  # ... before the levers and counterfactual experience: the plain learner
    del saved["train"]["counterfactual"]
    run = validate(stored_config(saved), resources=False)
    assert not run.planning.enabled and not run.train.compile_acting
    assert run.train.counterfactual.mode == "off" and run.train.target_tau == 1.0
    assert STORED_DEFAULTS == {"planning": {"enabled": False}, "train": {
        "compile_acting": False, "counterfactual": {"mode": "off"}, "target_tau": 1.0}}
    stated = OmegaConf.to_container(OmegaConf.structured(RunConfig()))  # a key it states: kept
    assert validate(stored_config(stated), resources=False).planning.enabled


def test_the_default_learner_is_the_recommended_one_and_the_others_are_one_override_away():
    """Issue 50: train's defaults (schema and conf/) train counterfactual experience with Polyak targets;
    preset=paper is the paper's learner (top-5 second update, hard copies); learner=plain the old default."""
    from crowdrl.training.learners import learner_of_preset, learner_settings, learners

    run = RunConfig()
    assert (run.train.counterfactual.mode, run.train.counterfactual.actions, run.train.counterfactual.k,
            run.train.target_tau) == ("second_update", "topk", 5, 0.005)
    for preset in ("demo", "episodes", "smoke"):
        train = _compose(f"preset={preset}")["train"]
        assert (train["counterfactual"]["mode"], train["target_tau"]) == ("second_update", 0.005), preset
    paper = _compose("preset=paper")["train"]
    assert (paper["counterfactual"]["mode"], paper["counterfactual"]["k"], paper["target_tau"]) == ("second_update", 5, 1.0)
    for overrides in (["learner=plain"], ["preset=paper", "learner=plain"], ["learner=plain", "preset=episodes"]):
        train = _compose(*overrides)["train"]
        assert (train["counterfactual"]["mode"], train["target_tau"]) == ("off", 1.0), overrides
    assert _compose("preset=paper", "train.target_tau=0.01")["train"]["target_tau"] == 0.01  # a key over the learner
    assert learners() == ("paper", "plain", "recommended")
    assert [learner_of_preset(p) for p in ("demo", "episodes", "paper", "smoke")] == ["recommended", "recommended",
                                                                                      "paper", "recommended"]
    assert learner_settings("recommended") == {"counterfactual": {"mode": "second_update", "actions": "topk", "k": 5},
                                               "target_tau": 0.005}


def test_the_demo_command_compiles_the_acting_network_at_the_demo_preset_only():
    from crowdrl.cli.demo import compose_run

    assert compose_run([])[1].train.compile_acting
    assert not compose_run(["train.compile_acting=false"])[1].train.compile_acting
    assert not compose_run(["preset=smoke"])[1].train.compile_acting
    cfg, run = compose_run(["seed=1"])
    assert cfg.train.compile_acting and run.planning.enabled and run.seed == 1


@pytest.mark.parametrize("name", ["evaluate", "export", "reproduce"])
def test_each_commands_yaml_states_its_typed_schemas_keys_and_defaults(name):
    """conf/<command>.yaml (what a user reads) and the command's typed schema (what Hydra checks it
    against) hold the same keys and defaults; the ones the yaml leaves to elsewhere: evaluate's env (the
    env group, null by default), reproduce's out (an interpolation of budget, planning, counterfactual)."""
    from dataclasses import asdict

    from omegaconf import OmegaConf

    from crowdrl.cli.schemas import EvaluateConfig, ExportConfig
    from crowdrl.reproduction.config import ReproduceConfig

    yaml = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / f"{name}.yaml"))
    assert yaml.pop("defaults")[0] == f"{name}_schema"  # composed onto the schema, as config.yaml onto run_schema
    yaml.pop("hydra")
    if name == "reproduce":
        schema = asdict(ReproduceConfig(out=yaml["out"]))
    else:
        schema = asdict({"evaluate": EvaluateConfig, "export": ExportConfig}[name]())
    if name == "evaluate":
        assert schema.pop("env")["scenario"] is None
    assert _flat(yaml) == _flat(schema)
