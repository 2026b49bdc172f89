"""The ceiling (crowdrl.sim.oracle, crowdrl.evaluation.ceiling, the ceiling command): every solved path replays
through CrowdNavEnv to success at the same step, crowd branches on new goals included; infeasible cases are
proven by exhaustive search; the gap to a policy is counted per case; a file of another stream is refused."""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import pytest
import torch

from crowdrl.evaluation.ceiling import (Ceiling, check_stream, compute_ceiling, crowd_identity, gap, read_ceiling,
                                        replay, write_ceiling)
from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT, advance, step
from crowdrl.sim.kinematics import action_table, decode_action, wrap_angle
from crowdrl.sim.oracle import INFEASIBLE, SOLVED, UNKNOWN, beam_search, check_searchable, exhaustive
from crowdrl.sim.scenarios import initial_states


@pytest.fixture(scope="module")
def circle_sample():
    """Circle test cases 0..11 (seed 0) at widths 64 then 512, and the config."""
    cfg = CrowdConfig(scenario="circle", num_humans=10)
    return cfg, compute_ceiling(cfg, cases=12, widths=(64, 512), chunk=12)


def test_every_solved_path_replays_through_the_env_to_success_at_its_step(circle_sample):
    cfg, ceiling = circle_sample
    assert ceiling.counts()[SOLVED] >= 11, ceiling.counts()
    assert replay(ceiling, cfg) == []
    # the times are plausible: 8 m less the goal radius at most 1 m/s (31 steps), within the time limit
    solved = [s for s, lab in zip(ceiling.steps, ceiling.labels) if lab == SOLVED]
    least = math.ceil((2 * cfg.circle_radius - cfg.robot_radius) / (cfg.robot_v_pref * cfg.time_step))
    assert all(least <= s <= cfg.max_steps for s in solved) and min(solved) == least


def test_replay_catches_a_wrong_path(circle_sample):
    """The exactness check can fail: a path cut short, or one step changed, is reported."""
    cfg, ceiling = circle_sample
    i = ceiling.labels.index(SOLVED)
    bad = dataclasses.replace(ceiling, actions=[list(a) for a in ceiling.actions], steps=list(ceiling.steps))
    bad.actions[i] = bad.actions[i][:-1] + [0]  # the last step stands still instead of arriving
    wrong = replay(bad, cfg, [i])
    assert len(wrong) == 1 and wrong[0].startswith(f"case {i}:")


def test_obstacle_scenarios_are_searched_with_their_walls():
    for scenario in ("doorway", "room"):
        cfg = CrowdConfig(scenario=scenario, num_humans=10)
        ceiling = compute_ceiling(cfg, cases=3, widths=(64,), chunk=3)
        assert ceiling.counts()[SOLVED] >= 2, (scenario, ceiling.counts())
        assert replay(ceiling, cfg) == [], scenario


def test_children_are_the_simulators_next_states_when_the_robot_changes_a_new_goal():
    """The search's step (humans once per crowd variant, then crowd.advance per child) equals crowd.step,
    on states where humans draw new goals and the robot stands where it changes the draw."""
    cfg = CrowdConfig(scenario="circle", num_humans=5, goal_steps_before_new_goal=1)
    start = initial_states(cfg, rng.episode_keys("test", 0, torch.arange(4)))
    # put every human on its goal, so each draws a new goal this step; the robot next to one of those goals
    state = start.replace(human_position=start.human_goal.clone())
    state = state.replace(robot_position=start.human_goal[:, 0] + torch.tensor([0.5, 0.0]))
    table = action_table(cfg.robot_v_pref)
    actions = torch.tensor([0, 3, 40, 80])
    vel, head = decode_action("unicycle", actions, state.robot_heading, table, cfg.robot_v_pref)
    want, _ = step(cfg, state, vel, head)
    from crowdrl.sim.humans import human_velocities

    hv, _ = human_velocities(cfg, state)
    got = advance(cfg, state, vel, wrap_angle(head), hv)
    for name in ("robot_position", "robot_heading", "human_position", "human_velocity", "human_goal", "human_goal_steps"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    # and the robot's position can change a draw: the same crowd with the robot elsewhere draws other goals
    changed = 0
    for x in torch.linspace(-4.5, 4.5, 7):
        for y in torch.linspace(-4.5, 4.5, 7):
            away = state.replace(robot_position=torch.tensor([[float(x), float(y)]]).expand(4, 2).clone())
            changed += int(not torch.equal(advance(cfg, away, vel, wrap_angle(head), hv).human_goal, got.human_goal))
    assert changed > 0


def test_search_tracks_crowd_variants_exactly():
    """Cases whose nodes drew different new goals carry several crowd variants, and their paths still replay."""
    cfg = CrowdConfig(scenario="circle", num_humans=10)
    ids = torch.arange(20)
    start = initial_states(cfg, rng.episode_keys("test", 0, ids))
    found = beam_search(cfg, start, width=64)
    assert max(found.variants) > 1  # the robot's path changed some human's new goal among the nodes kept
    labels = [SOLVED if s > 0 else UNKNOWN for s in found.steps]
    ceiling = Ceiling("circle", "test", 0, crowd_identity(cfg), labels, found.steps, found.actions)
    assert replay(ceiling, cfg) == []


def test_known_infeasible_case_is_proven_and_a_solvable_one_is_not():
    """Circle test case 142 (seed 0): a human spawned next to the robot walks straight at it; every action
    sequence collides within 3 steps. Case 0 has an escape."""
    cfg = CrowdConfig(scenario="circle", num_humans=10)
    start = initial_states(cfg, rng.episode_keys("test", 0, torch.tensor([142, 0])))
    assert exhaustive(cfg, start.index(torch.tensor([0])), 3) == [True]
    assert exhaustive(cfg, start.index(torch.tensor([1])), 2) == [False]
    with pytest.raises(ValueError, match="horizon"):
        exhaustive(cfg, start, 0)


def test_gap_counts_avoidable_and_unavoidable_failures_and_time_over():
    labels = [SOLVED, SOLVED, SOLVED, INFEASIBLE, UNKNOWN, SOLVED]
    steps = [10, 20, 30, -1, -1, 40]
    c = Ceiling("circle", "test", 0, {"time_step": 0.25}, labels, steps, [[0] * s if s > 0 else [] for s in steps])
    events = [SUCCESS, COLLISION, SUCCESS, COLLISION, SUCCESS, TIMEOUT]
    lengths = [14, 5, 30, 2, 50, 117]
    g = gap(c, events, lengths)
    assert g["avoidable_failures"] == 2 and g["unavoidable_failures"] == 1 and g["unknown_failures"] == 0
    assert g["beyond_ceiling"] == 1 and g["both_solved"] == 2
    assert g["time_over_ceiling"] == pytest.approx((4 * 0.25 + 0) / 2)
    assert g["ceiling_success"] == pytest.approx(4 / 6)
    with pytest.raises(ValueError, match="labels 6 cases, the evaluation ran 2"):
        gap(c, events[:2], lengths[:2])
    assert math.isnan(gap(c, [COLLISION] * 6, lengths)["time_over_ceiling"])


def test_a_ceiling_of_another_stream_is_refused_naming_the_mismatch(tmp_path, circle_sample):
    cfg, ceiling = circle_sample
    path = tmp_path / "c.json"
    write_ceiling(path, ceiling)
    back = read_ceiling(path)
    assert back.labels == ceiling.labels and back.actions == ceiling.actions
    check_stream(back, cfg, split="test", seed=0, cases=12)
    check_stream(back, dataclasses.replace(cfg, lidar_rays=8, orca_backend="compiled"), split="test", seed=0, cases=12)
    for kwargs, cfg2, word in ((dict(seed=1), cfg, "seed"), (dict(cases=10), cfg, "cases"),
                               (dict(split="val"), cfg, "split"),
                               ({}, dataclasses.replace(cfg, scenario="square"), "scenario"),
                               ({}, dataclasses.replace(cfg, num_humans=5), "num_humans"),
                               ({}, dataclasses.replace(cfg, human_model="linear"), "human_model")):
        asked = dict(split="test", seed=0, cases=12) | kwargs
        with pytest.raises(ValueError, match=word):
            check_stream(back, cfg2, **asked)


@pytest.mark.parametrize("text, word", [("garbage", "cannot be read as JSON"), ("[]", "not a crowdrl ceiling"),
                                        ('{"format": 1}', "malformed field")])
def test_a_malformed_ceiling_file_is_refused_naming_it(tmp_path, text, word):
    path = tmp_path / "c.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=word) as err:
        read_ceiling(path)
    assert str(path) in str(err.value)


def test_a_ceiling_file_whose_labels_disagree_with_its_paths_is_refused(tmp_path, circle_sample):
    _, ceiling = circle_sample
    data = ceiling.to_json()
    i = data["labels"].index(SOLVED)
    data["steps"][i] += 1
    path = tmp_path / "c.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=f"case {i} is 'solved'"):
        read_ceiling(path)


def test_a_visible_robot_or_holonomic_kinematics_has_no_ceiling():
    with pytest.raises(ValueError, match="robot_visible"):
        check_searchable(CrowdConfig(robot_visible=True))
    with pytest.raises(ValueError, match="robot_kinematics"):
        check_searchable(CrowdConfig(robot_kinematics="holonomic"))


def run_ceiling(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    from crowdrl.cli.ceiling import main

    monkeypatch.setattr(sys, "argv", ["ceiling.py", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    return stop.value.code, capsys.readouterr().err


@pytest.mark.parametrize("args, word", [
    (["env=mars"], "Could not find 'env/mars'"),
    (["widths=[0]"], "widths: every width must be an integer >= 1"),
    (["widths=[512,64]"], "widths: widths must increase"),
    (["cases=0"], "cases: must be an integer >= 1"),
    ([f"cases={2**63}"], "cases"),
    (["split=tset"], "split: must be one of"),
    (["horizon=9"], "horizon: at most 4"),
    (["cell=0"], "cell:"),
    (["env.robot_visible=true"], "env.robot_visible:"),
    (["chunk=0"], "chunk:"),
    (["wdiths=[1]"], "wdiths: not read by ceiling.py (unknown key)"),
])
def test_bad_ceiling_settings_exit_2_naming_the_key_with_nothing_written(monkeypatch, capsys, tmp_path, args, word):
    monkeypatch.chdir(tmp_path)
    extra = [] if any(a.startswith("cases") for a in args) else ["cases=2"]
    code, err = run_ceiling(monkeypatch, capsys, *args, *extra)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and word in lines[0], err
    assert list(tmp_path.iterdir()) == []


def test_the_ceiling_command_writes_a_replayed_file_and_never_overwrites(monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(tmp_path)
    main_args = ["env=circle", "cases=2", "widths=[32]", "out=c.json"]
    from crowdrl.cli.ceiling import main

    monkeypatch.setattr(sys, "argv", ["ceiling.py", *main_args])
    main()
    out = capsys.readouterr().out
    assert "every path replayed exactly" in out and (tmp_path / "c.json").is_file()
    before = (tmp_path / "c.json").read_bytes()
    code, err = run_ceiling(monkeypatch, capsys, *main_args)
    assert code == 2 and "out: c.json exists; pass overwrite=true" in err
    assert (tmp_path / "c.json").read_bytes() == before


def test_evaluate_reports_the_gap_and_refuses_a_ceiling_of_other_cases(tmp_path, circle_sample):
    from crowdrl.agents import evaluate_spec

    _, ceiling = circle_sample
    path = tmp_path / "c.json"
    write_ceiling(path, ceiling)
    record, _ = evaluate_spec(policy="orca", episodes=12, record_episode=None, ceiling=path)
    fails = round((1 - record["success_rate"]) * 12)
    assert record["avoidable_failures"] + record["unavoidable_failures"] + record["unknown_failures"] == fails
    assert record["ceiling"] == str(path) and record["both_solved"] + record["beyond_ceiling"] == 12 - fails
    for kwargs, word in ((dict(episodes=10), "cases"), (dict(seed=1), "seed"), (dict(scenario="square"), "scenario"),
                         (dict(num_humans=5), "num_humans")):
        with pytest.raises(ValueError, match=f"eval.ceiling: .*{word}"):
            evaluate_spec(policy="orca", record_episode=None, ceiling=path, **({"episodes": 12} | kwargs))


def test_the_ceiling_benchmark_prints_a_table_and_writes_json(tmp_path, capsys):
    import bench_ceiling

    out = tmp_path / "bench.json"
    assert bench_ceiling.main(["--cases", "2", "--widths", "16", "--json", str(out)]) == 0
    assert "min / 1000 cases" in capsys.readouterr().out
    row = json.loads(out.read_text())["rows"][0]
    assert row["scenario"] == "circle" and row["cases"] == 2 and row["s_per_case"] > 0
    assert row["solved"] + row["infeasible"] + row["unknown"] == 2
