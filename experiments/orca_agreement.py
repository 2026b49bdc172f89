"""ORCA agreement with RVO2, per branch: the 260 reference cases and fresh pyrvo scenes.

    python experiments/orca_agreement.py          # needs pyrvo (installed by `make install`)
    python experiments/orca_agreement.py --json

Uses the same scenes (:mod:`crowdrl.testing`) and exclusions as ``tests/test_orca.py`` (which
asserts |dv| <= 1e-4) and prints, per set and branch, the measured worst |dv| and how many agents
were bit-exact, then the agents excluded as ill-conditioned and the largest float32 speed.
"""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path

import numpy as np
import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim.orca import orca_solve
from crowdrl.testing import KINDS, ORCA_TOLERANCE, padded_batch, random_scene, rvo2_velocities

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
                         time_step=i["time_step"], neighbor_dist=i["neighbor_dist"],
                         max_neighbors=i["max_neighbors"], time_horizon=i["time_horizon"])
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
        params = dict(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0, mask=mask)
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
    columns = [Column("set"), Column("branch"), Column("worst_dv", "worst |dv| (m/s)", ".2e"), Column("agents"),
               Column("bit_exact", "bit-exact")]
    meta = {"tolerance": ORCA_TOLERANCE, "excluded_ill_conditioned": n_sens, "fresh_agents": n_all,
            "max_float32_speed": max_speed}
    return emit(rows, columns=columns, meta=meta, as_json=args.json,
                title="ORCA agreement with RVO2 per branch (feasible LP, 3-D fallback); ill-conditioned agents excluded",
                notes=[f"Ill-conditioned agents excluded (float64 moves them > {ORCA_TOLERANCE}): {n_sens}/{n_all}; "
                       f"largest float32 speed returned (max speed 1 m/s): {max_speed:.4f} m/s"])


if __name__ == "__main__":
    main()
