"""The Gymnasium face (``crowdrl/CircleCrossing-v0``, ``crowdrl/SquareCrossing-v0``)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import crowdrl  # noqa: F401  (registers the Gymnasium ids)
from crowdrl.gym_env import CrowdNavGymEnv

IDS = ["crowdrl/CircleCrossing-v0", "crowdrl/SquareCrossing-v0", "crowdrl/Doorway-v0"]
CHILD_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}


def _run_child(code: str, tmp_path) -> str:
    """Run ``code`` as a script file (spawned workers re-import it) in a fresh interpreter."""
    script = tmp_path / "child.py"
    script.write_text(textwrap.dedent(code))
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=CHILD_ENV,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum):UserWarning")
@pytest.mark.parametrize("env_id, kinematics", [(IDS[0], "unicycle"), (IDS[1], "unicycle"), (IDS[0], "holonomic")])
def test_gymnasium_env_checker(env_id, kinematics):
    env = gym.make(env_id, robot_kinematics=kinematics)
    check_env(env.unwrapped)  # with the render check: it makes the env again with render_mode="rgb_array"
    obs, info = env.reset(seed=0)
    assert obs["robot"].shape == (9,) and obs["humans"].shape == (10, 5)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float)
    assert set(info) == {"event", "min_separation", "discomfort_count", "episode_id"}
    assert all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in info.values())
    assert info["event"] in (0, 1, 2, 3)


def test_stable_baselines3_env_checker():
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3_checker.check_env(gym.make(IDS[0]).unwrapped, warn=False)


def test_gymnasium_matches_batched_env():
    from crowdrl.envs import CrowdNavEnv

    genv = gym.make("crowdrl/SquareCrossing-v0", split="test").unwrapped
    obs, _ = genv.reset(seed=4, options={"episode_id": 2})
    tenv = CrowdNavEnv("square", num_envs=3, split="test", seed=4)
    td = tenv.reset()
    torch.testing.assert_close(torch.as_tensor(obs["humans"]), td["humans"][2])
    for a in (3, 40, 80):
        obs, r, _, _, info = genv.step(a)
        td["action"] = torch.full((3,), a)
        td = tenv.step(td)
        assert r == pytest.approx(td["next", "reward"][2].item(), abs=1e-6)
        assert info["event"] == td["next", "event"][2].item()
        td = td["next"]
    torch.testing.assert_close(torch.as_tensor(obs["robot"]), td["robot"][2])


def test_holonomic_matches_batched_env():
    from crowdrl.envs import CrowdNavEnv

    genv = gym.make("crowdrl/CircleCrossing-v0", robot_kinematics="holonomic").unwrapped
    assert genv.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    obs, _ = genv.reset(seed=2)
    tenv = CrowdNavEnv("circle", num_envs=1, seed=2, robot_kinematics="holonomic")
    td = tenv.reset()
    for a in ([0.3, 0.5], [1.0, 1.0], [-1.0, 0.0]):  # [1, 1] is faster than v_pref: scaled to 1 m/s
        obs, r, *_ = genv.step(np.array(a, np.float32))
        td["action"] = torch.tensor([a])
        td = tenv.step(td)["next"]
        torch.testing.assert_close(torch.as_tensor(obs["robot"]), td["robot"][0])
    assert np.hypot(*obs["robot"][2:4]) == pytest.approx(1.0)


def test_gymnasium_rejects_bad_actions():
    env = gym.make("crowdrl/CircleCrossing-v0").unwrapped
    env.reset(seed=0)
    for bad in (81, -1, 3.0, True, np.array([1, 2])):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    env.step(np.int64(80))
    env.step(np.array(5))
    hol = gym.make("crowdrl/CircleCrossing-v0", robot_kinematics="holonomic").unwrapped
    hol.reset(seed=0)
    for bad in ([1.5, 0.0], [0.0, np.nan], [0.1, 0.2, 0.3], 3, "fast"):
        with pytest.raises(ValueError, match="action"):
            hol.step(bad)
    with pytest.raises(ValueError, match="robot_kinematics"):
        gym.make("crowdrl/CircleCrossing-v0", robot_kinematics="diff-drive")
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)
    with pytest.raises(ValueError, match="episode_id"):
        env.reset(options={"episode_id": -2})


def test_reset_options_are_checked_naming_the_option_and_its_range():
    """Issue 52 (D11): an episode id beyond int64 names the option's range (not numpy's 'Overflow when unpacking
    long long'); options that are no dict, or hold a misspelt key, are refused naming them and the keys allowed."""
    env = gym.make("crowdrl/CircleCrossing-v0").unwrapped
    for bad in (2**63, -1, 1.0, True, "3"):
        with pytest.raises(ValueError, match=r"options\['episode_id'\] must be an integer in 0\.\.2\*\*63-1"):
            env.reset(seed=0, options={"episode_id": bad})
    with pytest.raises(ValueError, match=r"options: unknown key\(s\) 'episod_id'; allowed: episode_id"):
        env.reset(seed=0, options={"episod_id": 3})
    for bad in ("junk", [1, 2], ("episode_id", 3)):
        with pytest.raises(ValueError, match=r"options must be None or a dict with the keys episode_id, got"):
            env.reset(seed=0, options=bad)
    first, _ = env.reset(seed=0, options={"episode_id": 2**63 - 1})
    assert env.reset(seed=0, options={"episode_id": np.int64(2**63 - 1)})[1]["episode_id"] == 2**63 - 1
    assert np.array_equal(env.reset(seed=0, options={"episode_id": 2**63 - 1})[0]["robot"], first["robot"])
    assert env.reset(seed=0, options={})[1]["episode_id"] == 0  # no option: the stream's next episode


def test_a_complex_holonomic_velocity_is_refused():
    """Issue 52 (D12): numpy would drop the imaginary part of ``1+1j`` (with only a warning); a bool is no speed."""
    hol = gym.make("crowdrl/CircleCrossing-v0", robot_kinematics="holonomic").unwrapped
    hol.reset(seed=0)
    for bad in (np.array([1 + 1j, 0]), [0.5 + 0j, 0.0], np.array([True, False]), np.array([0.1, 0.2], dtype=object)):
        with pytest.raises(ValueError, match="action must be a finite real velocity"):
            hol.step(bad)
    hol.step(np.array([0.5, 0], dtype=np.int64))  # integers and floats of any width are velocities
    hol.step(np.array([0.5, 0.25], dtype=np.float32))


def test_render_rgb_array():
    assert CrowdNavGymEnv.metadata == {"render_modes": ["rgb_array"], "render_fps": 4}
    env = gym.make("crowdrl/CircleCrossing-v0", render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.shape[2] == 3 and first.shape[0] > 100 and first.dtype == np.uint8
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 10  # robot, goal and humans drawn
    env.step(40)
    assert env.render().shape == first.shape and not np.array_equal(env.render(), first)
    plain = gym.make("crowdrl/CircleCrossing-v0")
    plain.reset(seed=0)
    assert plain.render() is None
    with pytest.raises(ValueError, match="render_mode"):
        CrowdNavGymEnv(render_mode="ansi")


def test_render_rgb_array_draws_the_obstacles():
    """A doorway frame shows its wall: the pixel at (-4.5, 0) m, on the wall and clear of every agent
    (spawns keep 0.5 m from it), is the obstacle colour; an open-space frame has none there."""
    from matplotlib.colors import to_rgb

    from crowdrl.viz.trajectory import OBSTACLE_COLOR

    def pixel(env, x, y):
        frame = env.render()
        hw, n = 6.0, frame.shape[0]  # the view is [-6, 6]^2 for every scenario (circle radius 4 m, square 10 m)
        return frame[int(round((hw - y) / (2 * hw) * n)), int(round((x + hw) / (2 * hw) * n))]

    wall = np.round(np.array(to_rgb(OBSTACLE_COLOR)) * 255)
    door = CrowdNavGymEnv("doorway", render_mode="rgb_array")
    door.reset(seed=0)
    assert np.abs(pixel(door, -4.5, 0.0).astype(float) - wall).max() <= 2
    circle = CrowdNavGymEnv("circle", render_mode="rgb_array")
    circle.reset(seed=0)
    assert np.abs(pixel(circle, -4.5, 0.0).astype(float) - wall).max() > 20


def _vec_episodes(venv, seed, resets: int) -> list[np.ndarray]:
    """The humans' start positions of ``resets`` successive resets (the first with ``seed``)."""
    out = [venv.reset(seed=seed)[0]["humans"]]
    out += [venv.reset()[0]["humans"] for _ in range(resets - 1)]
    return out


def test_make_vec_unseeded_sub_envs_differ_and_seeded_repeat():
    a, b = gym.make_vec(IDS[0], 4), gym.make_vec(IDS[0], 4)
    unseeded = _vec_episodes(a, None, 2)
    for humans in unseeded:
        assert len({h.tobytes() for h in humans}) == 4  # every sub-env its own episode
    assert not np.array_equal(unseeded[0], unseeded[1])  # and a new one on the next reset
    assert not np.array_equal(unseeded[0], _vec_episodes(b, None, 1)[0])  # another process-like draw
    seeded_a, seeded_b = _vec_episodes(a, 7, 3), _vec_episodes(b, 7, 3)
    for x, y in zip(seeded_a, seeded_b):
        np.testing.assert_array_equal(x, y)
    assert len({h.tobytes() for h in seeded_a[0]}) == 4  # seeds 7, 8, 9, 10: four streams
    # reset(seed=s) is scenario stream s, episodes 0, 1, ... (the same as the TorchRL env's)
    single = gym.make(IDS[0]).unwrapped
    np.testing.assert_array_equal(single.reset(seed=8)[0]["humans"], seeded_a[0][1])
    np.testing.assert_array_equal(single.reset()[0]["humans"], seeded_a[1][1])


def test_fresh_script_gym_make_leaves_torchrl_out_and_torchrl_gym_env_runs(tmp_path):
    # One fresh interpreter for both checks (each costs seconds of imports). As a user would
    # write it: torchrl's GymEnv(num_envs=...) runs an AsyncVectorEnv whose spawned workers
    # re-import the script, so the module-level `import crowdrl` registers the ids there too.
    out = _run_child(
        """
        import crowdrl

        if __name__ == "__main__":
            import multiprocessing, sys
            import gymnasium as gym
            import torch

            env = gym.make("crowdrl/CircleCrossing-v0")
            env.reset(seed=0)
            env.step(0)
            print("torchrl imported:", "torchrl" in sys.modules, multiprocessing.get_start_method(allow_none=True))

            from torchrl.envs import GymEnv

            torch.set_num_threads(1)
            env = GymEnv("crowdrl/CircleCrossing-v0", num_envs=3)
            try:
                td = env.rollout(5, break_when_any_done=False)
            finally:
                env.close()
            print("rollout:", tuple(td.batch_size), td["next", "event"].dtype, tuple(td["next", "humans"].shape))
        """,
        tmp_path,
    )
    lines = [ln for ln in out.splitlines() if ln.startswith(("torchrl imported:", "rollout:"))]
    assert lines == ["torchrl imported: False None", "rollout: (3, 5) torch.int64 (3, 5, 10, 5)"], out


def test_step_after_the_episode_ended_raises_until_reset():
    """Gymnasium's contract: no step() after terminated/truncated, until reset()."""
    env = gym.make(IDS[0], robot_kinematics="holonomic", num_humans=1)
    env.reset(seed=0)
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, _ = env.step(np.zeros(2, np.float32))  # standing still: a timeout
    with pytest.raises(RuntimeError, match=r"has (terminated|truncated): call reset\(\) before step\(\)"):
        env.step(np.zeros(2, np.float32))
    env.reset()
    env.step(np.zeros(2, np.float32))  # a new episode steps again
