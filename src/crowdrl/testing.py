"""Random ORCA scenes and their RVO2 answers (through pyrvo), for the tests and benchmarks.

Not used by the library itself. :func:`rvo2_velocities` needs ``pyrvo``, a test/benchmark-only
install (``make install``); it is imported when that function is called, so importing this module
does not need it.
"""

from __future__ import annotations

import numpy as np
import torch

KINDS = ("crowd", "dense", "overlap", "many")
ORCA_TOLERANCE = 1e-4  # m/s: the accepted |dv| between our ORCA and RVO2 on well-conditioned agents


def random_scene(rng: np.random.Generator, kind: str, n: int | None = None) -> dict[str, np.ndarray]:
    """One scene of ``kind`` (see :data:`KINDS`): positions, velocities, preferred velocities,
    radius and max speed, float32-exact. ``n`` agents, or a random count for the kind if ``None``.

    ``crowd``: spread over a 10 m square; ``dense``: clustered with surface gaps of 1-50 mm;
    ``overlap``: clustered, some overlapping by up to 0.15 m; ``many``: 12-40 agents of random
    radius. Radius 0.31 m (the humans' ORCA radius) except for ``many``; max speed 1 m/s.
    """
    counts = {"crowd": (2, 12), "dense": (4, 14), "overlap": (3, 10), "many": (12, 41)}
    if kind not in counts:
        raise ValueError(f"unknown scene kind {kind!r}; expected one of {KINDS}")
    if n is None:
        n = int(rng.integers(*counts[kind]))
    if kind == "dense":
        pos = _cluster(rng, n, gap_lo=1e-3, gap_hi=5e-2)
    elif kind == "overlap":
        pos = _cluster(rng, n, gap_lo=-0.15, gap_hi=0.02)
    else:
        pos = rng.uniform(-5, 5, (n, 2))
    radius = np.full(n, 0.31) if kind != "many" else rng.uniform(0.2, 0.4, n)
    speed = rng.uniform(0, 1, n)
    ang = rng.uniform(0, 2 * np.pi, n)
    vel = np.stack((speed * np.cos(ang), speed * np.sin(ang)), -1)
    goals = -pos + rng.normal(0, 0.5, (n, 2)) if kind in ("dense", "overlap") else rng.uniform(-5, 5, (n, 2))
    pref = goals - pos
    norm = np.linalg.norm(pref, axis=-1, keepdims=True)
    pref = np.where(norm > 1, pref / np.maximum(norm, 1e-9), pref)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return {"positions": f32(pos), "velocities": f32(vel), "pref_velocities": f32(pref),
            "radius": f32(radius), "max_speed": f32(np.ones(n))}


def _cluster(rng: np.random.Generator, n: int, gap_lo: float, gap_hi: float) -> np.ndarray:
    """Agents placed one by one touching an earlier one, with a surface gap in [gap_lo, gap_hi]."""
    pos = [np.zeros(2)]
    for _ in range(1, n):
        anchor = pos[int(rng.integers(len(pos)))]
        ang = rng.uniform(0, 2 * np.pi)
        dist = 0.62 + rng.uniform(gap_lo, gap_hi)
        pos.append(anchor + dist * np.array([np.cos(ang), np.sin(ang)]))
    return np.array(pos)


def rvo2_velocities(scene: dict[str, np.ndarray], *, time_step: float = 0.25, neighbor_dist: float = 10.0,
                    max_neighbors: int = 10, time_horizon: float = 5.0) -> np.ndarray:
    """One RVO2 ``doStep`` of ``scene`` through pyrvo: the new velocities ``[n, 2]`` (float64)."""
    import pyrvo

    sim = pyrvo.RVOSimulator(time_step, neighbor_dist, max_neighbors, time_horizon, 5.0, 0.3, 1.0)
    for p, v, r, m in zip(scene["positions"], scene["velocities"], scene["radius"], scene["max_speed"]):
        sim.add_agent(tuple(map(float, p)), neighbor_dist, max_neighbors, time_horizon, 5.0, float(r), float(m),
                      tuple(map(float, v)))
    for i, pv in enumerate(scene["pref_velocities"]):
        sim.set_agent_pref_velocity(i, tuple(map(float, pv)))
    sim.do_step()
    return np.array([sim.get_agent_velocity(i).to_tuple() for i in range(len(scene["positions"]))], dtype=np.float64)


def padded_batch(scenes: list[dict[str, np.ndarray]],
                 dtype: torch.dtype = torch.float32) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Stack scenes of different sizes into ``[B, Nmax]`` tensors and a presence mask ``[B, Nmax]``;
    absent agents sit at the origin with zero velocity (the mask, not the distance, excludes them)."""
    n_max = max(len(s["positions"]) for s in scenes)
    B = len(scenes)
    out = {k: torch.zeros(B, n_max, 2, dtype=dtype) for k in ("positions", "velocities", "pref_velocities")}
    out.update({k: torch.ones(B, n_max, dtype=dtype) for k in ("radius", "max_speed")})
    mask = torch.zeros(B, n_max, dtype=torch.bool)
    for b, s in enumerate(scenes):
        n = len(s["positions"])
        for k in out:
            out[k][b, :n] = torch.as_tensor(np.asarray(s[k]), dtype=dtype)
        mask[b, :n] = True
    return out, mask



def robot_centric_states(*batch: int, n: int = 10, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Plausible robot-centric states ``(robot_rc [*batch, 9], humans_rc [*batch, n, 5])`` for
    encoder tests: positions of a few metres, speeds ~1 m/s, drawn from torch's global RNG."""
    robot = torch.randn(*batch, 9, dtype=dtype)
    robot[..., :2] = 0
    robot[..., 4] = 0.3
    robot[..., 5] = 4 * torch.rand(batch, dtype=dtype) + 0.5
    robot[..., 6] = 0
    robot[..., 7] = 1.0
    humans = torch.randn(*batch, n, 5, dtype=dtype)
    humans[..., :2] *= 3
    humans[..., 4] = 0.6
    return robot, humans


class KilledRun(BaseException):
    """Stops a training run mid-update as SIGKILL would (a ``BaseException``: no handler of the run catches it)."""


def train_until_killed(run, folder, frame: int) -> None:
    """Train ``run`` into ``folder`` and kill it in the first update at ``frame`` collected frames
    (what an exact-resume test resumes from); fails if the run ends before that frame."""
    from crowdrl.training.pipeline import run_training
    from crowdrl.training.trainer import Trainer

    update_once = Trainer.update_once

    def dies_at_frame(self, sample):
        if self.counters.frames == frame:
            raise KilledRun(f"killed at frame {frame}")
        return update_once(self, sample)

    Trainer.update_once = dies_at_frame
    try:
        run_training(run, folder, render=False)
    except KilledRun:
        return
    finally:
        Trainer.update_once = update_once
    raise AssertionError(f"the run ended without an update at frame {frame}")


__all__ = ["KINDS", "ORCA_TOLERANCE", "KilledRun", "padded_batch", "random_scene", "robot_centric_states",
           "rvo2_velocities", "train_until_killed"]
