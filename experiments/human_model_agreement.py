"""The humans' batched models against their references, one step on fresh random scenes.

    python experiments/human_model_agreement.py --model orca --robot-visible --seed 0 --scenes 3000
    python experiments/human_model_agreement.py --model social_force --seed 0 --scenes 3000 --json
    python experiments/human_model_agreement.py --model social_force --backend compiled --seed 0 --scenes 3000

Scenes: :func:`crowdrl_testing.random_crowd_scene` (``crowd``, ``dense``, ``overlap`` in turn: a 10 m
square, clusters with mm gaps, overlapping clusters) with a robot at a random place and velocity. The
batched side is the simulator's own path (:func:`crowdrl.sim.humans.human_velocities` on a
:class:`~crowdrl.sim.state.CrowdState`, float32); the reference is

* ``orca``: RVO2 through ``pyrvo`` (``doStep``), the robot added last as one more agent (radius
  ``robot_radius + 0.01``, its velocity, max speed ``robot_v_pref``) when ``--robot-visible``;
  tolerance 1e-4 m/s, as ``experiments/orca_agreement.py``;
* ``social_force``: one call of the ``socialforce`` package (0.2.3), the robot one more pedestrian
  without a destination (NaN: it heads where it goes) and preferred speed ``robot_v_pref`` when
  ``--robot-visible``; tolerance 1e-4 m/s, as ORCA's. Both sides compute in float32 with the same
  operations in the same order (the package's autograd backward written out), and the answers come out
  bit-exact (on the 2-core CPU where this was measured: worst |dv| 0 over 3000 scenes); the tolerance
  leaves room for another kernel's rounding (the field of view's einsum, a GPU), which 10 sub-steps carry
  on and which, in mm-gap clusters, can flip a pair across the field of view's edge (weight 1 against
  0.5, ~1e-2 m/s). A modelling difference (the field of view, the 0.4 s potential step, a sub-step more
  or less, the speed cap) moves far more agents by far more.

It prints, per scene kind, the humans compared (the robot's own answer is not: the simulator discards
it), how many came within the tolerance and the worst |dv|; ``--json``'s ``agents`` and ``within`` are
the totals.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np
import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.humans import human_velocities
from crowdrl.sim.orca import OrcaParams
from crowdrl_testing import (CROWD_KINDS, ORCA_TOLERANCE, crowd_scene_state, random_crowd_scene, rvo2_velocities,
                             socialforce_velocities)

MODELS = ("orca", "social_force")
TOLERANCE = {"orca": ORCA_TOLERANCE, "social_force": 1e-4}  # m/s (the module's docstring says why)


def reference(cfg: CrowdConfig, scene: dict[str, np.ndarray]) -> np.ndarray:
    """The reference's new velocities of the scene's humans ``[n, 2]``."""
    pos, vel = scene["positions"], scene["velocities"]
    n = len(pos)
    if cfg.human_model == "orca":
        humans = {"positions": pos, "velocities": vel,
                  "pref_velocities": scene["goals"] - pos,  # float32, as the batched side computes it
                  "radius": np.full(n, cfg.human_radius + cfg.orca_radius_margin, np.float32),
                  "max_speed": np.full(n, cfg.human_v_pref, np.float32)}
        norm = np.linalg.norm(humans["pref_velocities"], axis=-1, keepdims=True)
        humans["pref_velocities"] = np.where(norm > 1, humans["pref_velocities"] / np.maximum(norm, 1e-12),
                                             humans["pref_velocities"]).astype(np.float32)
        if cfg.robot_visible:
            robot = {"positions": scene["robot_position"], "velocities": scene["robot_velocity"],
                     "pref_velocities": scene["robot_velocity"],
                     "radius": np.float32(cfg.robot_radius + cfg.orca_radius_margin),
                     "max_speed": np.float32(cfg.robot_v_pref)}
            humans = {k: np.concatenate((v, np.asarray(robot[k])[None])) for k, v in humans.items()}
        return rvo2_velocities(humans, OrcaParams.from_config(cfg))[:n]
    goals, speeds, has_goal = scene["goals"], np.full(n, cfg.human_v_pref), np.ones(n, bool)
    if cfg.robot_visible:
        pos, vel = np.concatenate((pos, scene["robot_position"][None])), np.concatenate((vel, scene["robot_velocity"][None]))
        goals, speeds = np.concatenate((goals, scene["robot_position"][None])), np.append(speeds, cfg.robot_v_pref)
        has_goal = np.append(has_goal, False)
    return socialforce_velocities(pos, vel, goals, speeds, has_goal, time_step=cfg.time_step,
                                  substeps=cfg.sf_substeps, tau=cfg.sf_tau, v0=cfg.sf_v0, sigma=cfg.sf_sigma)[:n]


def agreement(model: str, robot_visible: bool, seed: int, scenes: int, backend: str = "eager") -> list[dict]:
    """Per scene kind: ``agents`` (humans compared), ``within`` (of them within the tolerance), ``worst_dv``."""
    gen = np.random.default_rng(seed)
    drawn = [(CROWD_KINDS[k % len(CROWD_KINDS)], random_crowd_scene(gen, CROWD_KINDS[k % len(CROWD_KINDS)]))
             for k in range(scenes)]
    groups = defaultdict(list)  # one batch per (kind, crowd size): a fixed crowd, as the simulator's default
    for kind, scene in drawn:
        groups[kind, len(scene["positions"])].append(scene)
    tol = TOLERANCE[model]
    rows = {kind: {"kind": kind, "agents": 0, "within": 0, "worst_dv": 0.0} for kind in CROWD_KINDS}
    for (kind, n), batch in groups.items():
        cfg = CrowdConfig(num_humans=n, human_model=model, robot_visible=robot_visible, orca_backend=backend)
        ours, _ = human_velocities(cfg, crowd_scene_state(batch))
        for b, scene in enumerate(batch):
            err = np.linalg.norm(ours[b].double().numpy() - reference(cfg, scene), axis=-1)
            row = rows[kind]
            row["agents"] += n
            row["within"] += int((err <= tol).sum())
            row["worst_dv"] = max(row["worst_dv"], float(err.max()))
    return [r for r in rows.values() if r["agents"]]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", choices=MODELS, required=True)
    parser.add_argument("--robot-visible", action="store_true", help="the humans see the robot")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes (numpy)")
    parser.add_argument("--scenes", type=int, default=3000, help="fresh scenes (default 3000)")
    parser.add_argument("--backend", choices=("eager", "compiled"), default="eager",
                        help="the simulator's backend (env.orca_backend); compiled: one graph per crowd size")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    if args.scenes < 1:
        parser.error(f"--scenes must be >= 1, got {args.scenes}")
    torch.set_num_threads(1)
    rows = agreement(args.model, args.robot_visible, args.seed, args.scenes, args.backend)
    log(f"{args.model} done")
    agents, within = sum(r["agents"] for r in rows), sum(r["within"] for r in rows)
    for r in rows:
        r["share"] = r["within"] / r["agents"]
    tol = TOLERANCE[args.model]
    meta = {"model": args.model, "robot_visible": args.robot_visible, "backend": args.backend, "seed": args.seed,
            "scenes": args.scenes,
            "tolerance": tol, "reference": "pyrvo (RVO2 2.0)" if args.model == "orca" else "socialforce 0.2.3"}
    columns = [Column("kind"), Column("agents"), Column("within", f"within {tol:g} m/s"),
               Column("share", "share", ".4%"), Column("worst_dv", "worst |dv| (m/s)", ".2e")]
    return emit(rows, columns=columns, meta=meta, as_json=args.json, extra={"agents": agents, "within": within},
                title=f"{args.model} humans ({args.backend}){' seeing the robot' if args.robot_visible else ''} against "
                      f"{meta['reference']}: one step of {args.scenes} fresh scenes (seed {args.seed})",
                notes=[f"{within}/{agents} humans within {tol:g} m/s ({within / agents:.4%})"])


if __name__ == "__main__":
    main()
