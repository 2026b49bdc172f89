"""ORCA agreement with RVO2, per branch: the 260 reference cases, fresh pyrvo scenes, and fresh
scenes among static obstacles (walls, pillars, narrow gaps, concave polygons, rooms).

    python experiments/orca_agreement.py          # needs pyrvo (installed by `make install`)
    python experiments/orca_agreement.py --json

Uses the same scenes (:mod:`crowdrl_testing`) and exclusions as ``tests/test_orca.py`` and
``tests/test_orca_obstacles.py`` (which assert |dv| <= 1e-4) and prints, per set and branch, the
measured worst |dv| and how many agents were bit-exact (obstacle scenes: the share within 1e-4),
then the agents excluded as ill-conditioned and the largest float32 speed.
"""

from __future__ import annotations

import argparse
import gzip
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim.orca import OrcaParams, orca_solve
from crowdrl_testing import (KINDS, OBSTACLE_KINDS, ORCA_TOLERANCE, padded_batch, padded_obstacles, random_obstacle_scene,
                             random_scene, rvo2_velocities)

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--obstacle-scenes", type=int, default=200,
                        help="fresh obstacle scenes per (kind, time_horizon_obst) (default 200)")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    cases = json.load(gzip.open(ROOT / "tests" / "data" / "orca_cases.json.gz", "rt"))["cases"]
    worst = {"feasible": [0.0, 0, 0], "fallback": [0.0, 0, 0]}
    for c in cases:
        i, o = c["input"], c["output"]
        t = lambda k: torch.tensor(i[k]).unsqueeze(0)  # noqa: E731
        sol = orca_solve(t("positions"), t("velocities"), t("pref_velocities"), t("radius"), t("max_speed"),
                         OrcaParams(time_step=i["time_step"], neighbor_dist=i["neighbor_dist"],
                                    max_neighbors=i["max_neighbors"], time_horizon=i["time_horizon"]))
        err = np.linalg.norm(sol.velocities[0].double().numpy() - np.array(o["new_velocities"]), axis=-1)
        sens, inf = np.array(o["precision_sensitive"]), np.array(o["lp_infeasible"])
        for branch, m in (("feasible", ~inf & ~sens), ("fallback", inf & ~sens)):
            if m.any():
                w = worst[branch]
                w[0], w[1], w[2] = max(w[0], err[m].max()), w[1] + int(m.sum()), w[2] + int((err[m] == 0).sum())
    for b, (e, n, exact) in worst.items():
        rows.append({"set": f"reference cases ({len(cases)})", "branch": b, "worst_dv": float(e), "agents": n,
                     "bit_exact": exact})
    log("reference cases done")

    fresh = {"feasible": [0.0, 0], "fallback": [0.0, 0]}
    n_sens = n_all = 0
    max_speed = 0.0
    for kind in KINDS:
        gen = np.random.default_rng(1234 + KINDS.index(kind))
        scenes = [random_scene(gen, kind) for _ in range(300)]
        refs = [rvo2_velocities(s) for s in scenes]
        b32, mask = padded_batch(scenes)
        b64, _ = padded_batch(scenes, torch.float64)
        params = dict(params=OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0), mask=mask)
        v32, v64 = orca_solve(**b32, **params), orca_solve(**b64, **params).velocities
        for b, (s, ref) in enumerate(zip(scenes, refs)):
            n = len(s["positions"])
            v = v32.velocities[b, :n].double().numpy()
            err = np.linalg.norm(v - ref, axis=-1)
            sens = np.linalg.norm(v64[b, :n].numpy() - ref, axis=-1) > ORCA_TOLERANCE
            inf = v32.lp_infeasible[b, :n].numpy()
            n_sens, n_all = n_sens + int(sens.sum()), n_all + n
            max_speed = max(max_speed, float(np.linalg.norm(v, axis=-1).max()))
            for branch, m in (("feasible", ~inf & ~sens), ("fallback", inf & ~sens)):
                if m.any():
                    fresh[branch][0] = max(fresh[branch][0], err[m].max())
                    fresh[branch][1] += int(m.sum())
    for b, (e, n) in fresh.items():
        rows.append({"set": f"fresh scenes ({len(KINDS)} kinds x 300)", "branch": b, "worst_dv": float(e), "agents": n,
                     "bit_exact": None})
    log("fresh scenes done")
    obstacle_rows = obstacle_agreement(args.obstacle_scenes)
    rows += obstacle_rows
    columns = [Column("set"), Column("branch"), Column("worst_dv", "worst |dv| (m/s)", ".2e"), Column("agents"),
               Column("bit_exact", "bit-exact"), Column("within", "within 1e-4", ".4%")]
    meta = {"tolerance": ORCA_TOLERANCE, "excluded_ill_conditioned": n_sens, "fresh_agents": n_all,
            "max_float32_speed": max_speed,
            "obstacle_agents": sum(r["agents"] for r in obstacle_rows),
            "obstacle_within": sum(r["within_count"] for r in obstacle_rows)}
    return emit(rows, columns=columns, meta=meta, as_json=args.json,
                title="ORCA agreement with RVO2 per branch (feasible LP, 3-D fallback); ill-conditioned agents excluded",
                notes=[f"Ill-conditioned agents excluded (float64 moves them > {ORCA_TOLERANCE}): {n_sens}/{n_all}; "
                       f"largest float32 speed returned (max speed 1 m/s): {max_speed:.4f} m/s",
                       f"Obstacle scenes: {meta['obstacle_within']}/{meta['obstacle_agents']} agents within "
                       f"{ORCA_TOLERANCE} m/s ({meta['obstacle_within'] / meta['obstacle_agents']:.4%}, ill-conditioned "
                       f"included; the worst |dv| excludes them: "
                       f"{sum(r['ill_conditioned'] for r in obstacle_rows)} agents)"])


def obstacle_agreement(scenes_per_set: int) -> list[dict]:
    """Fresh scenes of every obstacle kind, at ``time_horizon_obst`` 5 s (the scenarios') and 2 s:
    per kind, the float32 answers' worst |dv| against RVO2 over the well-conditioned agents, and the
    share of all agents (ill-conditioned ones included) within the tolerance."""
    rows = []
    params = OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0)
    for kind in OBSTACLE_KINDS:
        worst, n_all, n_within, n_sens, n_obst = 0.0, 0, 0, 0, 0
        for tho in (5.0, 2.0):
            gen = np.random.default_rng(98765 + 10 * OBSTACLE_KINDS.index(kind) + int(tho))
            scenes = [random_obstacle_scene(gen, kind) for _ in range(scenes_per_set)]
            refs = [rvo2_velocities(s, replace(params, time_horizon_obst=tho)) for s in scenes]
            solved = {}
            for dtype in (torch.float32, torch.float64):
                batch, mask = padded_batch(scenes, dtype)
                obstacles, obstacle_mask = padded_obstacles(scenes, dtype)
                solved[dtype] = orca_solve(**batch, params=replace(params, time_horizon_obst=tho), mask=mask,
                                           obstacles=obstacles, obstacle_mask=obstacle_mask)
            for b, (s, ref) in enumerate(zip(scenes, refs)):
                n = len(s["positions"])
                err = np.linalg.norm(solved[torch.float32].velocities[b, :n].double().numpy() - ref, axis=-1)
                sens = np.linalg.norm(solved[torch.float64].velocities[b, :n].numpy() - ref, axis=-1) > ORCA_TOLERANCE
                n_all, n_within, n_sens = n_all + n, n_within + int((err <= ORCA_TOLERANCE).sum()), n_sens + int(sens.sum())
                n_obst += int((solved[torch.float32].num_obstacle_lines[b, :n] > 0).sum())
                if (~sens).any():
                    worst = max(worst, float(err[~sens].max()))
        rows.append({"set": f"obstacles: {kind} (2 x {scenes_per_set} scenes, tho 5 s and 2 s)", "branch": "all",
                     "worst_dv": worst, "agents": n_all, "bit_exact": None, "within": n_within / n_all,
                     "within_count": n_within, "ill_conditioned": n_sens, "with_obstacle_lines": n_obst})
        log(f"obstacles {kind} done")
    return rows


if __name__ == "__main__":
    main()
