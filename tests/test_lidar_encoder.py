"""The lidar scan as a network input (``encoder.lidar``): the scan's tokens, every encoder reading them, the
planner's predicted scans, a run that trains, tests and exports with them, and the keys' checks."""

from __future__ import annotations

import pytest
import torch

from crowdrl.envs import CrowdNavEnv
from crowdrl.models import ENCODERS
from crowdrl.models.predictor import ConstantVelocityPredictor
from crowdrl.models.qnet import make_q_network
from crowdrl.models.scan import SCAN_TOKENS, ScanTokens
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.config import CrowdConfig
from crowdrl.training import ConfigError, validate
from crowdrl.training.checkpoint import config_fingerprint
from crowdrl.training.config import to_dict
from crowdrl.training.pipeline import run_training

TINY = {"preset": "smoke", "seed": 0, "encoder": {"name": "sarl", "lidar": "conv"},
        "env": {"scenario": "corridor", "num_humans": 3, "lidar_rays": 24, "orca_backend": "eager"},
        "logger": {"name": "csv", "progress_bar": False, "render": False},
        "planning": {"enabled": True, "width": 3},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 96, "warmup_frames": 32, "batch_size": 16,
                  "buffer_size": 1000, "updates_per_frame": 0.25, "val_every_frames": 96, "val_episodes": 2,
                  "checkpoint_every_frames": 96, "test_episodes": 2, "compile_acting": False, "compile_loss": False}}


@pytest.mark.parametrize("kind", ["mlp", "conv"])
def test_scan_tokens_have_the_encoders_width_and_follow_the_scan(kind):
    torch.manual_seed(0)
    tokens = ScanTokens(kind, num_rays=30, max_range=4.0, token_dim=10)
    scan = torch.rand(2, 3, 30) * 4.0
    out = tokens(scan)
    assert out.shape == (2, 3, SCAN_TOKENS, 10)
    assert not torch.allclose(tokens(scan.roll(5, dims=-1)), out)  # the rays' order matters: ray 0 is the heading
    with pytest.raises(ValueError, match="lidar: expected 30 rays"):
        tokens(torch.zeros(2, 29))
    with pytest.raises(ValueError, match="kind: got 'cnn'"):
        ScanTokens("cnn", 30, 4.0, 5)
    with pytest.raises(ValueError, match="num_rays"):
        ScanTokens(kind, 0, 4.0, 5)


@pytest.mark.parametrize("encoder", sorted(ENCODERS))
def test_every_encoder_reads_the_scan_beside_the_crowd(encoder):
    """Q depends on the scan; with a crowd mask the absent humans still change nothing (padding-invariant);
    the encoder and the head start from the weights of the network without the scan."""
    torch.manual_seed(0)
    plain = make_q_network(encoder)
    torch.manual_seed(0)
    net = make_q_network(encoder, lidar="conv", lidar_rays=16, lidar_range=4.0)
    plain_state = plain.state_dict()
    for key, value in net.state_dict().items():
        if not key.startswith("scan."):
            assert torch.equal(value, plain_state[key]), key
    robot, humans = torch.randn(4, 9), torch.randn(4, 3, 5)
    scan = torch.rand(4, 16) * 4.0
    q = net(robot, humans, scan)
    assert q.shape == (4, 81)
    assert not torch.allclose(net(robot, humans, scan.flip(-1)), q)
    mask = torch.tensor([True, True, False]).expand(4, 3)
    padded = humans.clone()
    padded[:, 2] = 123.0
    torch.testing.assert_close(net(robot, padded, mask, scan), net(robot, humans[:, :2], scan), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="reads the lidar scan"):
        net(robot, humans)
    with pytest.raises(ValueError, match="reads no scan"):
        plain(robot, humans, mask, scan)


def test_the_keys_are_checked_and_the_scan_off_keeps_every_fingerprint():
    with pytest.raises(ConfigError, match=r"encoder.lidar: .*'cnn'"):
        validate({"encoder": {"lidar": "cnn"}, "env": {"lidar_rays": 8}})
    with pytest.raises(ConfigError, match=r"encoder.lidar: \(mlp\) reads the lidar scan, but env.lidar_rays is 0"):
        validate({"encoder": {"lidar": "mlp"}})
    now = to_dict(validate({}))
    before = {**now, "encoder": {k: v for k, v in now["encoder"].items() if k != "lidar"}}
    assert config_fingerprint(now) == config_fingerprint(before)  # stored runs, recorded before the key, still load
    scan = to_dict(validate({"encoder": {"lidar": "mlp"}, "env": {"lidar_rays": 8}}))
    assert config_fingerprint(scan) != config_fingerprint(to_dict(validate({"env": {"lidar_rays": 8}})))


def test_the_planner_reads_the_observed_scan_at_the_root_and_predicts_it_exactly_in_open_space():
    torch.manual_seed(0)
    cfg = CrowdConfig(scenario="circle", num_humans=5, min_humans=2, lidar_rays=36)
    env = CrowdNavEnv("circle", num_envs=6, num_humans=5, config=cfg, seed=1, split="val")
    net = make_q_network("sarl", lidar="mlp", lidar_rays=36, lidar_range=cfg.lidar_range)
    planner = OnlinePlanner(net, ConstantVelocityPredictor(cfg.time_step), cfg, gamma=0.97, depth=2, width=3,
                            lidar_key="lidar")
    assert planner.in_keys == ["robot", "humans", "humans_mask", "lidar"]
    td = env.reset()
    # the scan the planner computes for a state is the env's own (walls aside: none in open space)
    torch.testing.assert_close(planner.scan(td["robot"], td["humans"], td["humans_mask"]), td["lidar"],
                               atol=1e-5, rtol=0)
    plan = planner.plan(td["robot"], td["humans"], td["humans_mask"], lidar=td["lidar"])
    from crowdrl.envs.robot_centric import robot_centric

    robot_rc, humans_rc = robot_centric(td["robot"], td["humans"])
    torch.testing.assert_close(plan.action_value, net(robot_rc, humans_rc, td["humans_mask"], td["lidar"]))
    out = planner(td.clone())
    assert torch.equal(out["action"], plan.action)
    with pytest.raises(ValueError, match="lidar_rays is 0"):
        OnlinePlanner(net, ConstantVelocityPredictor(cfg.time_step), CrowdConfig(), gamma=0.97, lidar_key="lidar")


@pytest.mark.parametrize("scenario", ["corridor", "circle"])
def test_a_run_trains_tests_and_exports_with_the_scan(tmp_path, scenario):
    """The recommended learner (counterfactual experience, Polyak targets) with planning: the buffer keeps the
    scans, the actor, the planner and the counterfactual transitions read them, and the run tests. Its ONNX model
    takes the scan last (the planner whole in open space; the greedy Q policy among walls, whose planner reads
    edges the export does not take) and acts as the checkpoint does on test cases."""
    pytest.importorskip("onnxruntime")
    from crowdrl.agents import compare_on_test_cases
    from crowdrl.evaluation.report import read_eval_record
    from crowdrl.export import export_onnx, read_exported

    run = validate({**TINY, "env": {**TINY["env"], "scenario": scenario}})
    assert run.train.counterfactual.mode != "off"
    summary = run_training(run, tmp_path / "run")
    assert summary["frames"] == 96 and summary["updates"] > 0
    record = read_eval_record(tmp_path / "run" / "eval.json")
    assert record["episodes"] == 2 and record["scenario"] == scenario
    among_walls = scenario == "corridor"
    info = export_onnx(tmp_path / "run", tmp_path / "policy.onnx", planning={"depth": 0} if among_walls else None)
    assert info.max_q_error is not None and info.max_q_error < 1e-4  # onnxruntime against torch, random inputs
    model = read_exported(info.path)
    assert model.layout == ("entities_lidar" if among_walls else "world_lidar") and model.inputs[-1] == "lidar"
    assert model.metadata["crowdrl.lidar_rays"] == "24"
    compared = compare_on_test_cases(tmp_path / "run", info.path, episodes=4, batch=4)
    assert compared["steps"] > 0 and compared["differ"] == 0
    assert compared["onnx"]["success_rate"] == compared["torch"]["success_rate"]
    fewer = validate({**TINY, "env": {**TINY["env"], "scenario": scenario, "lidar_rays": 12}})
    from crowdrl.onnx_policy import OnnxPolicy
    from crowdrl.training.factories import make_env

    with pytest.raises(ValueError, match="env.lidar_rays: .* 24 rays, the env gives 12"):
        OnnxPolicy(model).check_env(make_env(fewer, split="test", num_envs=1))
