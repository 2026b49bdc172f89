"""Random ORCA scenes and their RVO2 answers (via pyrvo) for the agreement tests."""

from __future__ import annotations

import numpy as np

KINDS = ("crowd", "dense", "overlap", "many")


def random_scene(rng: np.random.Generator, kind: str) -> dict:
    """One scene: positions, velocities, preferred velocities, radius, max speed (float32-exact)."""
    if kind == "crowd":
        n = int(rng.integers(2, 12))
        pos = rng.uniform(-5, 5, (n, 2))
    elif kind == "dense":
        n = int(rng.integers(4, 14))
        pos = _cluster(rng, n, gap_lo=1e-3, gap_hi=5e-2)
    elif kind == "overlap":
        n = int(rng.integers(3, 10))
        pos = _cluster(rng, n, gap_lo=-0.15, gap_hi=0.02)
    elif kind == "many":
        n = int(rng.integers(12, 41))
        pos = rng.uniform(-5, 5, (n, 2))
    else:
        raise ValueError(kind)
    radius = np.full(n, 0.31) if kind != "many" else rng.uniform(0.2, 0.4, n)
    speed = rng.uniform(0, 1, n)
    ang = rng.uniform(0, 2 * np.pi, n)
    vel = np.stack((speed * np.cos(ang), speed * np.sin(ang)), -1)
    goals = -pos + rng.normal(0, 0.5, (n, 2)) if kind in ("dense", "overlap") else rng.uniform(-5, 5, (n, 2))
    pref = goals - pos
    norm = np.linalg.norm(pref, axis=-1, keepdims=True)
    pref = np.where(norm > 1, pref / np.maximum(norm, 1e-9), pref)
    f32 = lambda a: np.asarray(a, dtype=np.float32)
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


def rvo2_velocities(scene: dict, *, time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0) -> np.ndarray:
    import pyrvo

    sim = pyrvo.RVOSimulator(time_step, neighbor_dist, max_neighbors, time_horizon, 5.0, 0.3, 1.0)
    for p, v, r, m in zip(scene["positions"], scene["velocities"], scene["radius"], scene["max_speed"]):
        sim.add_agent(tuple(map(float, p)), neighbor_dist, max_neighbors, time_horizon, 5.0, float(r), float(m),
                      tuple(map(float, v)))
    for i, pv in enumerate(scene["pref_velocities"]):
        sim.set_agent_pref_velocity(i, tuple(map(float, pv)))
    sim.do_step()
    return np.array([sim.get_agent_velocity(i).to_tuple() for i in range(len(scene["positions"]))], dtype=np.float64)
