"""ORCA among static obstacles against RVO2 (pyrvo), the obstacle preprocessing, padding, bad input,
and the no-obstacle path kept bit-identical to before obstacles existed."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdrl.sim.obstacles import ObstacleEdges, process_obstacles
from crowdrl.sim.orca import OrcaParams, orca_solve, orca_velocities
from crowdrl_testing import (
    OBSTACLE_KINDS,
    ORCA_TOLERANCE,
    padded_batch,
    padded_obstacles,
    random_obstacle_scene,
    rvo2_velocities,
)

PARAMS = OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0)
BASELINE = Path(__file__).parent / "data" / "orca_no_obstacle_baseline.npz"
AGENT_KEYS = ("positions", "velocities", "pref_velocities", "radius", "max_speed")


def _bits(t: torch.Tensor) -> torch.Tensor:
    """The bit patterns of a float tensor (so that NaN == NaN when comparing)."""
    return t.view({torch.float32: torch.int32, torch.float64: torch.int64}[t.dtype]) if t.is_floating_point() else t


# --------------------------------------------------------------------------- no obstacles: as before
def test_no_obstacles_bit_identical_to_before_obstacles():
    """orca_solve's outputs at c377921 (tests/data/make_orca_no_obstacle_baseline.py): 240 scenes,
    float32/float64, with and without the presence mask; also with an empty obstacle set. Bit for bit,
    except float64 velocities within 1e-13: recorded on an AMD EPYC (AVX2), an Intel Xeon with AVX-512
    gives a few of them an ulp apart (at most 1.4e-14), whatever ATEN_CPU_CAPABILITY or MKL_CBWR says."""
    data = np.load(BASELINE)
    checked = 0
    for kind in sorted({k.split("/")[0] for k in data.files}):
        inputs = {k: torch.from_numpy(data[f"{kind}/in/{k}"]) for k in AGENT_KEYS}
        mask = torch.from_numpy(data[f"{kind}/in/mask"])
        tags = sorted({k.split("/")[1] for k in data.files if k.startswith(kind + "/") and "/in/" not in k})
        for tag in tags:
            dtype = torch.float32 if tag.startswith("float32") else torch.float64
            args = {k: v.to(dtype) for k, v in inputs.items()}
            m = mask if tag.endswith("_mask") and not tag.endswith("nomask") else None
            B = mask.shape[0]
            empty = dict(obstacles=torch.zeros(B, 2, 3, 2, dtype=dtype),
                         obstacle_mask=torch.zeros(B, 2, 3, dtype=torch.bool))
            for extra in ({}, empty):
                sol = orca_solve(**args, params=PARAMS, mask=m, **extra)
                for field in ("velocities", "lp_infeasible", "num_neighbors"):
                    want = torch.from_numpy(data[f"{kind}/{tag}/{field}"])
                    got = getattr(sol, field)
                    if dtype == torch.float64 and field == "velocities":  # an ulp apart across CPUs (see above)
                        torch.testing.assert_close(got, want, atol=1e-13, rtol=0, equal_nan=True,
                                                   msg=lambda m: f"{(kind, tag, field, bool(extra))}: {m}")
                    else:
                        assert torch.equal(_bits(got), _bits(want)), (kind, tag, field, bool(extra))
                checked += 1
    assert checked == 2 * 10


# --------------------------------------------------------------------------- against RVO2
def _solve(scenes, dtype, tho, **kw):
    batch, mask = padded_batch(scenes, dtype)
    obstacles, obstacle_mask = padded_obstacles(scenes, dtype)
    return orca_solve(**batch, params=replace(PARAMS, time_horizon_obst=tho), mask=mask, obstacles=obstacles,
                      obstacle_mask=obstacle_mask, **kw), mask


@pytest.mark.parametrize("kind", OBSTACLE_KINDS)
@pytest.mark.parametrize("tho", [5.0, 2.0])
def test_fresh_obstacle_scenes_agree_with_rvo2(kind, tho):
    """40 scenes per (kind, time_horizon_obst), 400 in all (about 2200 agents), generated here and
    stepped by RVO2 with the same polygons: every well-conditioned agent within ORCA_TOLERANCE."""
    pytest.importorskip("pyrvo")
    gen = np.random.default_rng(4321 + 10 * OBSTACLE_KINDS.index(kind) + int(tho))
    scenes = [random_obstacle_scene(gen, kind) for _ in range(40)]
    refs = [rvo2_velocities(s, replace(PARAMS, time_horizon_obst=tho)) for s in scenes]
    s32, mask = _solve(scenes, torch.float32, tho)
    v64 = _solve(scenes, torch.float64, tho)[0].velocities
    n_agents = n_within = n_sensitive = 0
    for b, (s, ref) in enumerate(zip(scenes, refs)):
        n = len(s["positions"])
        err = np.linalg.norm(s32.velocities[b, :n].double().numpy() - ref, axis=-1)
        # as in test_orca: where float64 itself moves the answer by more than the tolerance, the
        # float32 result is rounding noise
        sensitive = np.linalg.norm(v64[b, :n].numpy() - ref, axis=-1) > ORCA_TOLERANCE
        bad = np.flatnonzero((err > ORCA_TOLERANCE) & ~sensitive)
        assert bad.size == 0, f"{kind} scene {b}: agents {bad} off by {err[bad]}"
        n_agents += n
        n_within += int((err <= ORCA_TOLERANCE).sum())
        n_sensitive += int(sensitive.sum())
    assert n_within >= 0.999 * n_agents, (n_within, n_agents)
    assert n_sensitive <= 0.02 * n_agents, (n_sensitive, n_agents)
    # the scenes exercise the obstacle rules: obstacle lines, and hard ones in the 3-D fallback
    n_lines = s32.num_obstacle_lines[mask]
    assert (n_lines > 0).float().mean() > 0.5
    assert int((s32.lp_infeasible[mask] & (n_lines > 0)).sum()) >= 5


def test_obstacle_line_counts_match_rvo2():
    """Per agent, the obstacle lines plus the agent lines are RVO2's ORCA lines (its numObstLines:
    the covered, ignored and foreign-leg edges are skipped as RVO2 skips them)."""
    pyrvo = pytest.importorskip("pyrvo")
    gen = np.random.default_rng(2024)
    scenes = [random_obstacle_scene(gen, kind) for kind in OBSTACLE_KINDS for _ in range(20)]
    sol, _ = _solve(scenes, torch.float32, 3.0)
    checked = 0
    for b, s in enumerate(scenes):
        sim = pyrvo.RVOSimulator(PARAMS.time_step, PARAMS.neighbor_dist, PARAMS.max_neighbors, PARAMS.time_horizon, 3.0,
                                 0.3, 1.0)
        for polygon in s["obstacles"]:
            sim.add_obstacle([tuple(map(float, v)) for v in polygon])
        sim.process_obstacles()
        for p, v, r, m, pv in zip(s["positions"], s["velocities"], s["radius"], s["max_speed"], s["pref_velocities"]):
            i = sim.add_agent(tuple(map(float, p)), PARAMS.neighbor_dist, PARAMS.max_neighbors, PARAMS.time_horizon, 3.0,
                              float(r), float(m), tuple(map(float, v)))
            sim.set_agent_pref_velocity(i, tuple(map(float, pv)))
        sim.do_step()
        for i in range(len(s["positions"])):
            total = int(sol.num_obstacle_lines[b, i] + sol.num_neighbors[b, i])
            assert total == sim.get_agent_num_orca_lines(i), (b, i)
            checked += 1
    assert checked > 300 and int(sol.num_obstacle_lines.sum()) > 300


def test_obstacle_scenes_split_edges_like_rvo2():
    """process_obstacles makes the edges RVO2's processObstacles makes (split ones included)."""
    pyrvo = pytest.importorskip("pyrvo")
    gen = np.random.default_rng(99)
    scenes = [random_obstacle_scene(gen, kind) for kind in OBSTACLE_KINDS for _ in range(20)]
    edges = process_obstacles(*padded_obstacles(scenes))
    n_split = 0
    for b, s in enumerate(scenes):
        sim = pyrvo.RVOSimulator()
        for polygon in s["obstacles"]:
            sim.add_obstacle([tuple(map(float, v)) for v in polygon])
        before = sim.get_num_obstacle_vertices()
        sim.process_obstacles()
        n = sim.get_num_obstacle_vertices()
        n_split += n > before
        vertex = lambda i: sim.get_obstacle_vertex(i).to_tuple()  # noqa: E731
        want = sorted((vertex(i), vertex(sim.get_next_obstacle_vertex(i))) for i in range(n))
        valid = edges.valid[b]
        got = sorted((tuple(map(float, edges.start[b, e])), tuple(map(float, edges.end[b, e])))
                     for e in range(edges.num_edges) if valid[e])
        assert len(got) == len(want), b
        np.testing.assert_allclose(np.array(got), np.array(want), rtol=0, atol=1e-5)
    assert n_split >= 10, n_split


def test_wall_ahead_limits_the_normal_speed():
    """Straight at a wall 0.7 m away (radius 0.3): ORCA allows (0.7 / time_horizon_obst) m/s."""
    pos = torch.tensor([[[0.0, -1.0]]])
    wall = torch.tensor([[[[-5.0, 0.0], [5.0, 0.0]]]])
    v = orca_velocities(pos, torch.zeros_like(pos), torch.tensor([[[0.0, 1.0]]]), torch.full((1, 1), 0.3),
                        torch.ones(1, 1), replace(PARAMS, time_horizon_obst=2.0), obstacles=wall)
    torch.testing.assert_close(v, torch.tensor([[[0.0, 0.35]]]))


# --------------------------------------------------------------------------- padding, preprocessing
def test_padding_batching_and_preprocessing_do_not_change_the_answer():
    """A padded batch, extra empty polygons and vertex slots, and ObstacleEdges processed once all
    give, bit for bit, each scene's answer alone with its unpadded polygons."""
    gen = np.random.default_rng(5)
    scenes = [random_obstacle_scene(gen, kind) for kind in OBSTACLE_KINDS for _ in range(6)]
    batch, mask = padded_batch(scenes)
    obstacles, obstacle_mask = padded_obstacles(scenes)
    B, P, V, _ = obstacles.shape
    big = torch.full((B, P + 2, V + 3, 2), float("nan"))  # masked vertices may hold anything
    big_mask = torch.zeros(B, P + 2, V + 3, dtype=torch.bool)
    big[:, 1:P + 1, :V], big_mask[:, 1:P + 1, :V] = obstacles, obstacle_mask
    kw = dict(params=replace(PARAMS, time_horizon_obst=3.0), mask=mask)
    padded = orca_solve(**batch, obstacles=obstacles, obstacle_mask=obstacle_mask, **kw)
    bigger = orca_solve(**batch, obstacles=big, obstacle_mask=big_mask, **kw)
    edges = process_obstacles(obstacles, obstacle_mask)
    assert isinstance(edges, ObstacleEdges)
    processed = orca_solve(**batch, obstacles=edges, **kw)
    for sol in (bigger, processed):
        assert torch.equal(_bits(sol.velocities), _bits(padded.velocities))
        assert torch.equal(sol.num_obstacle_lines, padded.num_obstacle_lines)
    for b, s in enumerate(scenes):
        n = len(s["positions"])
        one = {k: torch.as_tensor(s[k]).unsqueeze(0) for k in AGENT_KEYS}
        polys = s["obstacles"]
        v = max(len(p) for p in polys)
        obs = torch.zeros(1, len(polys), v, 2)
        om = torch.zeros(1, len(polys), v, dtype=torch.bool)
        for p, poly in enumerate(polys):
            obs[0, p, :len(poly)], om[0, p, :len(poly)] = torch.as_tensor(poly), True
        alone = orca_solve(**one, params=replace(PARAMS, time_horizon_obst=3.0), obstacles=obs, obstacle_mask=om)
        assert torch.equal(_bits(alone.velocities[0]), _bits(padded.velocities[b, :n])), b
        # absent agents keep their velocity and have no obstacle lines
        assert torch.equal(padded.velocities[b, n:], batch["velocities"][b, n:])
        assert int(padded.num_obstacle_lines[b, n:].sum()) == 0


def test_walls_are_convex_at_both_ends_and_polygons_by_their_turns():
    square_with_dent = torch.tensor([[[[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [1.0, 1.0], [0.0, 2.0]],
                                      [[3.0, 0.0], [4.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]])
    m = torch.tensor([[[True] * 5, [True, True, False, False, False]]])
    e = process_obstacles(square_with_dent, m)
    assert int(e.valid.sum()) == 7  # 5 edges of the polygon, 2 of the wall (one per side)
    starts = {tuple(map(float, e.start[0, i])): bool(e.start_convex[0, i]) for i in range(7)}
    assert starts[(1.0, 1.0)] is False and starts[(0.0, 0.0)] and starts[(2.0, 2.0)]
    assert starts[(3.0, 0.0)] and starts[(4.0, 0.0)]


# --------------------------------------------------------------------------- bad input
def _agents(B=1, N=2):
    pos = torch.tensor([[-3.0, 0.0], [3.0, 0.0]]).expand(B, N, 2).contiguous()
    return (pos, torch.zeros(B, N, 2), torch.zeros(B, N, 2), torch.full((B, N), 0.3), torch.ones(B, N))


SQUARE = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]


@pytest.mark.parametrize(
    "polygons, mask, words",
    [
        ([SQUARE, [[5.0, 5.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]], [[True] * 4, [True, False, False, False]],
         ["obstacles", r"polygon \(b=0, p=1\)", "1 vertex"]),
        ([SQUARE, SQUARE[::-1]], None, ["obstacles", r"polygon \(b=0, p=1\)", "clockwise"]),
        ([SQUARE, [[0.0, 0.0], [float("nan"), 1.0], [1.0, 1.0], [0.0, 1.0]]], None,
         ["obstacles", r"polygon \(b=0, p=1\)", "NaN"]),
        ([[[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]], None, ["obstacles", "zero-length"]),
        ([SQUARE], [[True, False, True, True]], ["obstacle_mask", "first"]),
    ],
)
def test_bad_polygons_name_the_argument_and_the_polygon(polygons, mask, words):
    obstacles = torch.tensor([polygons])
    obstacle_mask = None if mask is None else torch.tensor([mask])
    for call in (lambda: process_obstacles(obstacles, obstacle_mask),
                 lambda: orca_velocities(*_agents(), PARAMS, obstacles=obstacles, obstacle_mask=obstacle_mask)):
        with pytest.raises(ValueError) as info:
            call()
        for word in words:
            assert re.search(word, str(info.value)), (word, str(info.value))


def test_clockwise_walls_are_fine():
    """Two vertices are a wall, seen from both sides: their order does not matter."""
    a = orca_velocities(*_agents(), PARAMS, obstacles=torch.tensor([[[[0.0, -1.0], [0.0, 1.0]]]]))
    b = orca_velocities(*_agents(), PARAMS, obstacles=torch.tensor([[[[0.0, 1.0], [0.0, -1.0]]]]))
    assert torch.isfinite(a).all() and torch.isfinite(b).all()


@pytest.mark.parametrize(
    "kw, word, error",
    [
        (dict(obstacles=torch.zeros(1, 1, 4, 2, device="meta")), "obstacles is on meta", ValueError),
        (dict(obstacles=torch.tensor([[SQUARE]]), obstacle_mask=torch.ones(1, 1, 4, dtype=torch.bool, device="meta")),
         "obstacle_mask is on meta", ValueError),
        (dict(obstacles=torch.tensor([[SQUARE]], dtype=torch.float64)), "obstacles", TypeError),
        (dict(obstacles=torch.tensor([[SQUARE]] * 2)), "obstacles", ValueError),
        (dict(obstacles=torch.tensor([SQUARE])), "obstacles", ValueError),
        (dict(obstacles=torch.tensor([[SQUARE]]), obstacle_mask=torch.ones(1, 1, 3, dtype=torch.bool)),
         "obstacle_mask", ValueError),
        (dict(obstacle_mask=torch.ones(1, 1, 4, dtype=torch.bool)), "obstacle_mask", ValueError),
        (dict(obstacles=torch.tensor([[SQUARE]]), time_horizon_obst=0.0), "time_horizon_obst", ValueError),
    ],
)
def test_bad_obstacle_arguments_name_the_argument(kw, word, error):
    kw = dict(kw)
    tho = kw.pop("time_horizon_obst", None)
    with pytest.raises(error, match=word):
        orca_velocities(*_agents(), replace(PARAMS, time_horizon_obst=tho), **kw)


def test_processed_obstacles_on_another_device_are_rejected():
    edges = process_obstacles(torch.tensor([[SQUARE]]))
    on_meta = ObstacleEdges(*(t.to("meta") for t in edges))
    with pytest.raises(ValueError, match="obstacles is on meta"):
        orca_velocities(*_agents(), PARAMS, obstacles=on_meta)
