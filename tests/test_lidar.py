"""The 2-D lidar scan: exact distances to walls and discs, masks and padding, the heading
convention, batching, and the ``"lidar"`` observation of the envs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from crowdrl_testing import fresh_network
from crowdrl.envs import CrowdNavEnv
from crowdrl.sim.config import MAX_LIDAR_RAYS, CrowdConfig
from crowdrl.sim.lidar import lidar_angles, lidar_scan, observe_lidar
from crowdrl.sim.obstacles import obstacle_segments

D = torch.float64


def _segs(*pairs, valid=None):
    """One scene's segments ``((ax, ay), (bx, by)), ...`` as the batched triple."""
    start = torch.tensor([[p[0] for p in pairs]], dtype=D)
    end = torch.tensor([[p[1] for p in pairs]], dtype=D)
    mask = torch.ones(1, len(pairs), dtype=torch.bool) if valid is None else torch.tensor([valid])
    return start, end, mask


def _discs(*centres, radius=0.5, valid=None):
    c = torch.tensor([list(centres)], dtype=D)
    mask = torch.ones(1, len(centres), dtype=torch.bool) if valid is None else torch.tensor([valid])
    return c, radius, mask


def _scan(num_rays=4, max_range=10.0, origin=(0.0, 0.0), heading=0.0, **kw):
    return lidar_scan(torch.tensor([origin], dtype=D), torch.tensor([heading], dtype=D), num_rays, max_range, **kw)[0]


def test_a_wall_ahead_and_at_90_degrees_reads_its_exact_distance():
    wall_ahead = _segs(((3.0, -1.0), (3.0, 1.0)))
    assert _scan(segments=wall_ahead).tolist() == [3.0, 10.0, 10.0, 10.0]
    wall_left = _segs(((-1.0, 2.0), (1.0, 2.0)))  # ray 1 is 90° counter-clockwise from the heading
    assert _scan(segments=wall_left)[1].item() == pytest.approx(2.0, abs=1e-12)
    assert _scan(segments=wall_left)[[0, 2, 3]].tolist() == [10.0] * 3
    # oblique: a wall x = 3 seen along a ray at 45° (8 rays: ray 1), 3 / cos 45°
    assert _scan(8, segments=_segs(((3.0, -10.0), (3.0, 10.0))))[1].item() == pytest.approx(3 * math.sqrt(2), abs=1e-12)
    # a wall through the origin reads 0 on the rays that cross it, a wall along a ray its near end
    assert _scan(segments=_segs(((0.0, -1.0), (0.0, 1.0))))[[0, 2]].tolist() == [0.0, 0.0]
    assert _scan(segments=_segs(((2.0, 0.0), (5.0, 0.0))))[0].item() == 2.0


def test_a_disc_reads_the_distance_to_its_surface_and_zero_from_inside():
    scan = _scan(discs=_discs((0.0, -3.0), radius=0.5))
    assert scan[3].item() == pytest.approx(2.5, abs=1e-12) and scan[[0, 1, 2]].tolist() == [10.0] * 3
    # off-centre: a ray at height 0.3 meets a disc of radius 0.5 at x = 4 - 0.4
    assert _scan(origin=(0.0, 0.3), discs=_discs((4.0, 0.0)))[0].item() == pytest.approx(3.6, abs=1e-12)
    assert _scan(origin=(0.0, 0.6), discs=_discs((4.0, 0.0)))[0].item() == 10.0  # passes above it
    assert _scan(discs=_discs((0.2, 0.1)), num_rays=16).tolist() == [0.0] * 16  # the origin inside
    assert _scan(discs=_discs((4.0, 0.0)), origin=(8.0, 0.0))[0].item() == 10.0  # behind the ray


def test_the_nearest_hit_wins_and_readings_are_clipped_at_the_range():
    walls = _segs(((5.0, -1.0), (5.0, 1.0)), ((2.0, -1.0), (2.0, 1.0)))
    discs = _discs((3.0, 0.0), (1.5, 0.0), radius=0.25)
    assert _scan(segments=walls)[0].item() == 2.0
    assert _scan(segments=walls, discs=discs)[0].item() == pytest.approx(1.25, abs=1e-12)
    assert _scan(max_range=1.0, segments=walls, discs=discs)[0].item() == 1.0
    assert _scan(max_range=3.5).tolist() == [3.5] * 4  # nothing at all
    assert _scan(max_range=3.5, segments=walls[:2] + (torch.zeros(1, 2, dtype=torch.bool),)).tolist() == [3.5] * 4


def test_masked_entries_are_ignored_and_padding_changes_nothing():
    wall = ((2.0, -1.0), (2.0, 1.0))
    hidden = ((1.0, -1.0), (1.0, 1.0))
    base = _scan(16, segments=_segs(wall), discs=_discs((0.0, 2.0)))
    masked = _scan(16, segments=_segs(hidden, wall, valid=[False, True]),
                   discs=_discs((0.0, 1.0), (0.0, 2.0), (0.3, 0.0), valid=[False, True, False]))
    assert torch.equal(base, masked)
    padded = _scan(16, segments=_segs(wall, hidden, hidden, valid=[True, False, False]),
                   discs=_discs((0.0, 2.0), (0.0, 0.0), valid=[True, False]))
    assert torch.equal(base, padded)
    empty = (torch.zeros(1, 0, 2, dtype=D), torch.zeros(1, 0, 2, dtype=D), torch.zeros(1, 0, dtype=torch.bool))
    assert torch.equal(_scan(16, segments=empty, discs=_discs((0.0, 2.0))), _scan(16, discs=_discs((0.0, 2.0))))


def _scene(seed: int, B: int = 5, E: int = 4, N: int = 3):
    g = torch.Generator().manual_seed(seed)
    origin = torch.rand(B, 2, generator=g, dtype=D) * 2 - 1
    heading = torch.rand(B, generator=g, dtype=D) * 2 * math.pi
    start = torch.rand(B, E, 2, generator=g, dtype=D) * 8 - 4
    end = start + torch.rand(B, E, 2, generator=g, dtype=D) * 4 - 2
    valid = torch.rand(B, E, generator=g) < 0.8
    centres = torch.rand(B, N, 2, generator=g, dtype=D) * 8 - 4
    radii = torch.rand(B, N, generator=g, dtype=D) * 0.5 + 0.1
    mask = torch.rand(B, N, generator=g) < 0.8
    return origin, heading, (start, end, valid), (centres, radii, mask)


def _reference(origin, heading, R, max_range, segments, discs):
    """One ray, one entity at a time: a 2x2 solve per segment, the quadratic's smaller root per disc."""
    out = []
    for r in range(R):
        a = float(heading) + 2 * math.pi * r / R
        d = torch.tensor([math.cos(a), math.sin(a)], dtype=D)
        best = max_range
        for s, e, ok in zip(*segments):
            if not ok:
                continue
            m = torch.stack((d, s - e), 1)  # origin + t d = s + u (e - s)
            if abs(float(torch.linalg.det(m))) < 1e-12:
                continue
            t, u = torch.linalg.solve(m, s - origin).tolist()
            if t >= 0 and 0 <= u <= 1:
                best = min(best, t)
        for c, rad, ok in zip(*discs):
            if not ok:
                continue
            w = origin - c
            b, cc = float(w @ d), float(w @ w) - float(rad) ** 2
            if cc <= 0:
                best = 0.0
            elif b * b - cc >= 0 and -b - math.sqrt(b * b - cc) >= 0:
                best = min(best, -b - math.sqrt(b * b - cc))
        out.append(best)
    return torch.tensor(out, dtype=D)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1, 3, 8, 16]))
def test_batched_scans_equal_a_per_ray_per_entity_reference(seed, R):
    origin, heading, segs, discs = _scene(seed)
    scan = lidar_scan(origin, heading, R, 5.0, segments=segs, discs=discs)
    assert scan.shape == (5, R) and scan.dtype == D
    for i in range(5):
        one = lidar_scan(origin[i:i + 1], heading[i:i + 1], R, 5.0, segments=tuple(t[i:i + 1] for t in segs),
                         discs=tuple(t[i:i + 1] for t in discs))
        assert torch.equal(one[0], scan[i])  # batching changes nothing
        ref = _reference(origin[i], heading[i], R, 5.0, tuple(t[i] for t in segs), tuple(t[i] for t in discs))
        torch.testing.assert_close(scan[i], ref, rtol=0, atol=1e-9)


def test_the_scan_turns_with_the_heading_and_not_with_the_world():
    origin, heading, segs, discs = _scene(7, B=3)
    R = 12
    scan = lidar_scan(origin, heading, R, 6.0, segments=segs, discs=discs)
    # ray 0 along the heading, counter-clockwise: turning the robot by k rays shifts the scan by k
    turned = lidar_scan(origin, heading + 3 * 2 * math.pi / R, R, 6.0, segments=segs, discs=discs)
    torch.testing.assert_close(turned, scan.roll(-3, dims=1), rtol=0, atol=1e-9)
    # rotating and shifting the whole scene (robot included) leaves the scan as it was
    a, shift = 0.7, torch.tensor([1.5, -2.0], dtype=D)
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=D)
    move = lambda p: p @ rot.T + shift  # noqa: E731
    moved = lidar_scan(move(origin), heading + a, R, 6.0, segments=(move(segs[0]), move(segs[1]), segs[2]),
                       discs=(move(discs[0]), discs[1], discs[2]))
    torch.testing.assert_close(moved, scan, rtol=0, atol=1e-9)
    angles = lidar_angles(torch.tensor([0.5], dtype=D), 4)[0].tolist()
    assert angles == pytest.approx([0.5, 0.5 + math.pi / 2, 0.5 + math.pi, 0.5 + 3 * math.pi / 2])


def test_bad_arguments_and_config_values_are_refused_naming_them():
    o, h = torch.zeros(2, 2), torch.zeros(2)
    for rays in (0, -1, True, 2.5):
        with pytest.raises(ValueError, match="num_rays"):
            lidar_scan(o, h, rays, 4.0)
    for rng in (0.0, -1.0, math.inf, math.nan, True):
        with pytest.raises(ValueError, match="max_range"):
            lidar_scan(o, h, 4, rng)
    with pytest.raises(ValueError, match="heading"):
        lidar_scan(o, torch.zeros(3), 4, 4.0)
    for rays in (-1, True, 2.5, 1025, 100_000_000):
        with pytest.raises(ValueError, match="lidar_rays"):
            CrowdConfig(lidar_rays=rays)
    assert CrowdConfig(lidar_rays=MAX_LIDAR_RAYS).lidar_rays == 1024
    for rng in (0.0, -2.0, math.inf, math.nan, True):
        with pytest.raises(ValueError, match="lidar_range"):
            CrowdConfig(lidar_range=rng)
    assert CrowdConfig().lidar_rays == 0 and CrowdConfig().lidar_range == 4.0


@pytest.mark.parametrize("scenario", ["circle", "corridor", "doorway"])
def test_the_env_observes_the_scan_of_its_state(scenario):
    from torchrl.envs.utils import check_env_specs

    cfg = CrowdConfig(scenario, lidar_rays=16, lidar_range=3.0)
    env = CrowdNavEnv(scenario, num_envs=4, config=cfg, seed=2)
    assert env.observation_spec["lidar"].shape == (4, 16)
    check_env_specs(env)

    def expected(s):
        segs = obstacle_segments(s.obstacles, s.obstacle_mask) if s.has_obstacles else None
        return lidar_scan(s.robot_position, s.robot_heading, 16, 3.0, segments=segs,
                          discs=(s.human_position, cfg.human_radius, s.human_mask))

    td = env.reset()
    assert td["lidar"].shape == (4, 16) and torch.equal(td["lidar"], expected(env.state))
    for _ in range(3):
        td = env.rand_step(td)
        assert torch.equal(td["next", "lidar"], expected(env.state))
        assert torch.equal(observe_lidar(cfg, env.state), td["next", "lidar"])
        assert bool((td["next", "lidar"] <= 3.0).all() and (td["next", "lidar"] >= 0).all())
        td = td["next"]
    assert "lidar" not in CrowdNavEnv(scenario, num_envs=2).reset().keys()
    assert "lidar" not in CrowdNavEnv(scenario, num_envs=2).observation_spec.keys()


def test_the_corridor_walls_are_seen_sideways_at_reset():
    """The robot starts at (0, -4) facing +y, between walls at x = -2 and 2 (4 rays: ray 1 looks at -x)."""
    cfg = CrowdConfig("corridor", lidar_rays=4, lidar_range=5.0)
    env = CrowdNavEnv("corridor", num_envs=3, config=cfg, seed=0)
    td = env.reset()
    s = env.state
    walls = lidar_scan(s.robot_position, s.robot_heading, 4, 5.0, segments=obstacle_segments(s.obstacles, s.obstacle_mask))
    px = s.robot_position[:, 0]
    torch.testing.assert_close(walls[:, 1], 2.0 + px)
    torch.testing.assert_close(walls[:, 3], 2.0 - px)
    assert bool((td["lidar"] <= walls).all())  # humans only shorten readings


def test_training_builds_envs_and_actors_that_ignore_the_scan():
    from crowdrl.models.predictor import ConstantVelocityPredictor
    from crowdrl.training import ConfigError, validate
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict
    from crowdrl.training.factories import make_actor, make_env

    small = {"train": {"num_envs": 2, "compile_acting": False}}
    for scenario in ("circle", "doorway"):
        run = validate({"env": {"scenario": scenario, "lidar_rays": 8}, **small})
        env = make_env(run)
        td = env.reset()
        assert td["lidar"].shape == (2, 8)
        actor = make_actor(run, env, fresh_network(run), ConstantVelocityPredictor(0.25))
        assert "lidar" not in actor.in_keys
        out = env.rollout(2, actor, break_when_any_done=False)
        assert out["next", "lidar"].shape == (2, 2, 8)
    with pytest.raises(ConfigError, match="env.lidar_rays"):
        validate({"env": {"lidar_rays": -1}})
    # issue 52 (D8): an upper bound, checked before anything is allocated (1e8 rays reached 9.3 GB, then a traceback)
    with pytest.raises(ConfigError, match=r"env.lidar_rays must be an integer in 0\.\.1024 .*got 100000000"):
        validate({"env": {"lidar_rays": 100_000_000}}, resources=False)
    with pytest.raises(ConfigError, match="env.lidar_range"):
        validate({"env": {"lidar_range": 0.0}})
    # without a scan the lidar keys leave a run's fingerprint as it was before they existed
    now = to_dict(validate({}))
    before = {**now, "env": {k: v for k, v in now["env"].items() if not k.startswith("lidar_")}}
    assert config_fingerprint(now) == config_fingerprint(before)
    assert config_fingerprint(to_dict(validate({"env": {"lidar_range": 2.0}}))) == config_fingerprint(now)
    assert config_fingerprint(to_dict(validate({"env": {"lidar_rays": 8}}))) != config_fingerprint(now)


def test_the_hydra_env_group_takes_the_lidar_keys():
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from crowdrl.training import validate
    from crowdrl.training.config import RunConfig
    from crowdrl.training.resolvers import register_resolvers

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    register_resolvers()
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["env=doorway", "env.lidar_rays=16", "env.lidar_range=3.5"])
        plain = compose(config_name="config", overrides=["env=square"])
    run = validate(cfg, resources=False)
    assert (run.env.lidar_rays, run.env.lidar_range) == (16, 3.5)
    assert (plain.env.lidar_rays, plain.env.lidar_range) == (0, 4.0)


def test_the_gymnasium_face_observes_the_scan():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import crowdrl  # noqa: F401  (registers the ids)

    env = gym.make("crowdrl/Corridor-v0", lidar_rays=8).unwrapped
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    assert obs["lidar"].shape == (8,) and env.observation_space["lidar"].contains(obs["lidar"])
    batched = CrowdNavEnv("corridor", num_envs=1, seed=3, config=CrowdConfig("corridor", lidar_rays=8)).reset()
    assert obs["lidar"].tolist() == batched["lidar"][0].tolist()
    assert "lidar" not in gym.make("crowdrl/CircleCrossing-v0").reset(seed=0)[0]
