"""How far RVO2's float32 ORCA overshoots the max speed, by crowd size.

    python experiments/orca_overshoot.py [--scenes 3000] [--json]   # needs pyrvo (`make install`)

For N = 5, 10, 20, 30, 50 agents: random ``crowd`` scenes of :mod:`crowdrl_testing` (positions
uniform in a 10 m square, radius 0.31 m as the humans' ORCA radius, random current velocities and
goals, max speed 1 m/s) with the humans' ORCA parameters, fixed seeds. Prints the largest speed returned by our float32 ORCA
(:func:`crowdrl.sim.orca.orca_velocities`), by pyrvo's RVO2 (float32 C++) and by our float64
ORCA, with the number of agents above 1 m/s and above 1.01 m/s.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim.orca import OrcaParams, orca_velocities
from crowdrl_testing import random_scene, rvo2_velocities

SIZES = (5, 10, 20, 30, 50)
PARAMS = OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0)
LIMITS = {"over": 1.0 + 1e-6, "over_1.01": 1.01}  # above the limit beyond float32 rounding; by 1 %+


def measure(n: int, scenes: int, seed: int) -> dict[str, float | int]:
    """Largest speed and agents above the limits over ``scenes`` random scenes of ``n`` agents."""
    rng = np.random.default_rng(seed)
    batch = [random_scene(rng, "crowd", n) for _ in range(scenes)]
    stacked = {k: np.stack([s[k] for s in batch]) for k in batch[0]}
    speeds = {}
    for name, dtype in (("ours_f32", torch.float32), ("ours_f64", torch.float64)):
        t = {k: torch.as_tensor(v).to(dtype) for k, v in stacked.items()}
        v = orca_velocities(**t, params=PARAMS)
        speeds[name] = torch.linalg.vector_norm(v.double(), dim=-1).numpy()
    speeds["rvo2"] = np.stack([np.linalg.norm(rvo2_velocities(s, PARAMS), axis=-1) for s in batch])
    out: dict[str, float | int] = {"N": n, "scenes": scenes, "seed": seed}
    for name, s in speeds.items():
        out[f"max_{name}"] = float(s.max())
        for label, limit in LIMITS.items():
            out[f"{label}_{name}"] = int((s > limit).sum())
    return out


def main(argv: list[str] | None = None) -> list[dict[str, float | int]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=3000, help="random scenes per crowd size")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    if args.scenes < 1:
        parser.error(f"--scenes must be >= 1, got {args.scenes}")
    torch.set_num_threads(1)
    rows = []
    for n in SIZES:
        rows.append(measure(n, args.scenes, seed=1000 + n))
        log(f"N={n}: RVO2 max speed {rows[-1]['max_rvo2']:.4f} m/s")
    cell = lambda k: Column(lambda r: f"{r[f'max_{k}']:.4f} ({r[f'over_{k}']}/{r[f'over_1.01_{k}']})",  # noqa: E731
                            {"ours_f32": "ours float32", "rvo2": "RVO2 (pyrvo)", "ours_f64": "ours float64"}[k])
    columns = [Column("N"), Column(lambda r: r["N"] * r["scenes"], "agents"), cell("ours_f32"), cell("rvo2"),
               cell("ours_f64")]
    emit(rows, columns=columns, as_json=args.json, meta={"scenes": args.scenes, "limit_m_s": 1.0, **PARAMS},
         title=f"Max speed returned (limit 1 m/s) over {args.scenes} scenes per N; in parentheses: agents above "
               "1 m/s / above 1.01 m/s")
    return rows


if __name__ == "__main__":
    main()
