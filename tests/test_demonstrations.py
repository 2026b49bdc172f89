"""The oracle as a teacher (train.demonstrations): the stored demonstrations are the env's own transitions of
the oracle's paths; the key is checked, neutral when off, and a resumed run never adds them again."""

from __future__ import annotations

import json
import sys

import pytest
import torch
from torchrl.envs.utils import step_mdp

from crowdrl.evaluation.report import read_eval_record
from crowdrl.training import ConfigError, Trainer, validate
from crowdrl.training.checkpoint import config_fingerprint
from crowdrl.training.config import to_dict
from crowdrl.training.demonstrations import DEMO_FIRST_EPISODE, add_demonstrations, solve_cases
from crowdrl.training.counterfactual import WORLD_KEYS
from crowdrl.training.facts import RunFacts
from crowdrl.training.factories import make_buffer, make_env

TINY = {"preset": "smoke", "env": {"num_humans": 4},
        "logger": {"name": "csv", "progress_bar": False, "render": False},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 64, "warmup_frames": 32, "batch_size": 16,
                  "buffer_size": 1000, "updates_per_frame": 0.25, "target_update_frames": 32, "val_every_frames": 64,
                  "val_episodes": 2, "checkpoint_every_frames": 64, "test_episodes": 2, "compile_acting": False,
                  "compile_loss": False}}


def tiny(**train) -> dict:
    return {**TINY, "train": {**TINY["train"], **train}}


@pytest.mark.parametrize("n_step", [1, 3])
def test_stored_demonstrations_are_the_env_transitions_of_the_oracle_paths(n_step):
    torch.manual_seed(0)
    run = validate(tiny(n_step=n_step, counterfactual={"mode": "second_update"}))
    env = make_env(run, split="train", num_envs=1)
    facts = RunFacts.of(run)
    cfg = env.base_env.config
    buffer = make_buffer(run.train, facts)
    stored = facts.replay_keys() + WORLD_KEYS  # counterfactual experience's keys
    rng_before = torch.get_rng_state()
    report = add_demonstrations(buffer, lambda n: make_env(run, split="train", num_envs=n), cfg, run.seed, 5, [8, 32],
                                stored)
    assert torch.equal(torch.get_rng_state(), rng_before)  # the global RNG is left as it was
    paths = solve_cases(cfg, run.seed, 5, [8, 32])
    assert report.solved == len(paths.episodes) == report.stored_paths > 0
    assert report.transitions == len(buffer) == sum(len(a) for a in paths.actions)
    assert all(e >= DEMO_FIRST_EPISODE for e in paths.episodes)
    # the expected transitions: each path stepped alone through a fresh env, in the buffer's order (by length)
    order = sorted(range(len(paths.episodes)), key=lambda j: len(paths.actions[j]))
    want = {k: [] for k in ("action", "reward", "done", "terminated", "next_robot", "next_humans", "robot", "steps")}
    for j in order:
        one = make_env(run, split="train", num_envs=1)
        one.base_env.load_episodes(torch.tensor([paths.episodes[j]]))
        td = one.reset()
        rewards, dones, terms, nexts, nexth, robots = [], [], [], [], [], []
        for a in paths.actions[j]:
            td["action"] = torch.tensor([a])
            robots.append(td["robot_rc"][0].clone())
            out = one.step(td)
            rewards.append(float(out["next", "reward"]))
            dones.append(bool(out["next", "done"]))
            terms.append(bool(out["next", "terminated"]))
            nexts.append(out["next", "robot_rc"][0].clone())
            nexth.append(out["next", "humans_rc"][0].clone())
            td = step_mdp(out)
        assert dones[-1] and not any(dones[:-1]) and int(out["next", "event"]) == 1  # the path succeeds
        L, gamma = len(rewards), run.train.gamma
        for t in range(L):
            m = min(n_step, L - t)  # the window runs to the path's end at most
            want["reward"].append(sum(gamma ** k * rewards[t + k] for k in range(m)))
            want["done"].append(dones[t + m - 1])
            want["terminated"].append(terms[t + m - 1])
            want["next_robot"].append(nexts[t + m - 1])
            want["next_humans"].append(nexth[t + m - 1])
            want["robot"].append(robots[t])
            want["action"].append(paths.actions[j][t])
            want["steps"].append(m)
    got = buffer[:]
    assert got["action"].reshape(-1).tolist() == want["action"]
    torch.testing.assert_close(got["next", "reward"].reshape(-1), torch.tensor(want["reward"], dtype=torch.float32))
    assert got["next", "done"].reshape(-1).tolist() == want["done"]
    assert got["next", "terminated"].reshape(-1).tolist() == want["terminated"]
    assert got["steps_to_next_obs"].reshape(-1).tolist() == want["steps"]
    assert torch.equal(got["robot_rc"], torch.stack(want["robot"]))
    assert torch.equal(got["next", "robot_rc"], torch.stack(want["next_robot"]))
    assert torch.equal(got["next", "humans_rc"], torch.stack(want["next_humans"]))


@pytest.mark.parametrize("demo, words", [
    ({"cases": -1}, "train.demonstrations.cases: must be an integer in 0..train.buffer_size"),
    ({"cases": 1001}, "train.demonstrations.cases: must be an integer in 0..train.buffer_size (1000"),
    ({"widths": []}, "train.demonstrations.widths: must be a non-empty list"),
    ({"widths": [0]}, "train.demonstrations.widths: must be a non-empty list of integers in 1..2048"),
    ({"widths": [64, 16]}, "train.demonstrations.widths: must increase"),
])
def test_demonstration_keys_out_of_range_are_refused_naming_them(demo, words):
    with pytest.raises(ConfigError) as err:
        validate(tiny(demonstrations=demo))
    assert str(err.value).startswith(words.split(":")[0]) and words in str(err.value)


def test_demonstrations_need_humans_that_ignore_the_robot():
    visible = {"num_humans": 4, "robot_visible": True}
    off = {"mode": "off"}  # counterfactual experience would be refused first
    with pytest.raises(ConfigError, match=r"^train\.demonstrations\.cases: the oracle"):
        validate({**tiny(demonstrations={"cases": 10}, counterfactual=off), "env": visible})
    validate({**tiny(counterfactual=off), "env": visible})  # off: nothing to refuse


def test_a_bad_demonstration_key_is_one_line_exit_2_on_the_command_line(tmp_path):
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, str(root / "experiments" / "train.py"), "train.demonstrations.cases=-3",
                           f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, cwd=tmp_path,
                          timeout=120)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "train.demonstrations.cases" in lines[0], proc.stderr
    assert not (tmp_path / "run").exists()


def test_demonstrations_off_leave_the_fingerprint_as_before_the_key():
    off = to_dict(validate(tiny()))
    before = {**off, "train": {k: v for k, v in off["train"].items() if k != "demonstrations"}}
    assert config_fingerprint(off) == config_fingerprint(before)
    on = to_dict(validate(tiny(demonstrations={"cases": 10})))
    assert config_fingerprint(on) != config_fingerprint(off)


def test_a_resumed_run_keeps_its_demonstrations_and_never_adds_them_again(tmp_path):
    run = validate(tiny(demonstrations={"cases": 3, "widths": [8, 32]}, save_buffer=True))
    trainer = Trainer(run, tmp_path)
    try:
        first = trainer.train()
    finally:
        trainer.close()
    demos = trainer.counters.demo_transitions
    assert demos > 0 and len(trainer.buffer) == demos + first["frames"] and first["timers_s"]["demo"] > 0
    assert first["frames"] == 64 and first["episodes"] == trainer.counters.episodes  # demos are not frames
    longer = validate(tiny(demonstrations={"cases": 3, "widths": [8, 32]}, save_buffer=True, total_frames=128))
    resumed = Trainer(longer, tmp_path)
    try:
        second = resumed.train()
    finally:
        resumed.close()
    assert second["frames"] == 128 and resumed.counters.demo_transitions == demos
    assert len(resumed.buffer) == demos + 128  # the saved buffer's demonstrations, none added again
    assert second["timers_s"]["demo"] == first["timers_s"]["demo"]
    rows = [json.loads(line) for line in (tmp_path / "scalars.jsonl").read_text().splitlines()]
    demo_rows = [r for r in rows if r["kind"] == "demo"]
    assert len(demo_rows) == 1 and demo_rows[0]["train/demo_transitions"] == demos


def test_a_killed_run_with_demonstrations_resumed_with_its_buffer_is_bit_identical(tmp_path):
    """Killed mid-update at frame 224 (last checkpoint: frame 192), then resumed: the same final weights, test
    metrics and logged rows (but the wall-clock time/ columns) as the run never stopped; the demonstrations are
    added once, by the first process."""
    from crowdrl_testing import train_until_killed
    from crowdrl.training.checkpoint import load_checkpoint
    from crowdrl.training.pipeline import run_training

    run = validate({"logger": {"name": "csv", "progress_bar": False, "render": False}, "preset": "smoke",
                    "env": {"num_humans": 4}, "exploration": {"anneal_frames": 288},
                    "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 288, "buffer_size": 1000,
                              "batch_size": 16, "warmup_frames": 32, "updates_per_frame": 0.25,
                              "target_update_frames": 64, "val_every_frames": 96, "val_episodes": 4,
                              "checkpoint_every_frames": 64, "test_episodes": 4, "save_buffer": True,
                              "compile_loss": False, "counterfactual": {"mode": "second_update", "k": 3},
                              "demonstrations": {"cases": 3, "widths": [8, 32]}}})
    run_training(run, tmp_path / "ref")
    train_until_killed(run, tmp_path / "run", frame=224)
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["counters"]["frames"] == 192
    run_training(run, tmp_path / "run")

    def final(folder):
        last = load_checkpoint(folder / "checkpoints" / "last.pt")
        rows = [{k: v for k, v in json.loads(line).items() if not k.startswith("time/")}
                for line in (folder / "scalars.jsonl").read_text().splitlines()]
        return last, read_eval_record(folder / "eval.json"), rows

    (ref, ref_metrics, ref_rows), (got, metrics, rows) = final(tmp_path / "ref"), final(tmp_path / "run")
    assert ref["counters"]["demo_transitions"] == got["counters"]["demo_transitions"] > 0
    assert all(torch.equal(ref["loss"][k], got["loss"][k]) for k in ref["loss"])
    assert metrics == ref_metrics
    same = [(a == b) or (a != a and b != b) for ra, rb in zip(ref_rows, rows) for a, b in
            ((ra.get(k), rb.get(k)) for k in set(ra) | set(rb))]
    assert len(rows) == len(ref_rows) and all(same)
    assert sum(r["kind"] == "demo" for r in rows) == 1
