"""The intrinsic bonuses outside crowds: a hard-exploration Gymnasium task, several arms x seeds.

    python experiments/gym_study.py                                   # MountainCar-v0 -> results/gym-mountaincar
    python experiments/gym_study.py --seeds 0 1 --arms none re3 --out /tmp/gym

Each run is ``experiments/gym_intrinsic.py`` (TorchRL's DQN on the env, ε 1 -> 0.05 over 10k
frames, the bonus computed when the buffer is sampled) with the arm's flags; its JSON summary is
written to ``<out>/runs/<arm>-s<seed>.json`` and skipped when present, so a killed study resumes.
``<out>/table.md`` gives, per arm over seeds: the episodes until the goal was first reached, the
episodes that reached it, and the success rate over the last 20 episodes (mean [95 % bootstrap
CI, rliable]). In MountainCar an episode that terminates has reached the goal.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

import gym_intrinsic  # noqa: E402

from crowdrl.evaluation.stats import mean_interval  # noqa: E402
from crowdrl.files import atomic_write_bytes, atomic_write_json  # noqa: E402
from crowdrl.tables import markdown_table  # noqa: E402

STABLE = ["--reward-norm", "batch", "--center", "--clip", "5", "--obs-norm"]
ARMS = {
    "none": ["--bonus", "none"],
    "icm": ["--bonus", "icm"],
    "re3": ["--bonus", "re3"],
    "icm-stable": ["--bonus", "icm", *STABLE, "--feature-norm", "layernorm"],
    "re3-stable": ["--bonus", "re3", *STABLE],
    "rnd": ["--bonus", "rnd", "--obs-norm", "--reward-norm", "std"],  # as conf/exploration/rnd.yaml (Burda et al.)
}
COLUMNS = (("first_terminated_episode", "episodes to first goal", 0), ("terminated_episodes", "episodes at the goal", 0),
           ("final_terminated_rate", "success, last 20 episodes", 2))


def run_arm(arm: str, seed: int, env: str, frames: int, beta: float) -> dict:
    args = [*ARMS[arm], "--env", env, "--frames", str(frames), "--beta", str(beta), "--seed", str(seed)]
    out = gym_intrinsic.main(args)
    out.pop("last_sample", None)
    return {"arm": arm, "argv": args, **out}


def table(records: dict[str, list[dict]], reps: int) -> str:
    lines = ["Mean over seeds [95 % bootstrap CI, rliable]; a seed that never reached the goal counts "
             "its episodes to the first goal as the number of episodes it ran (a lower bound).", ""]
    rows = []
    for arm, recs in records.items():
        cells = []
        for key, _, digits in COLUMNS:
            values = np.array([r["episodes"] if key == "first_terminated_episode" and r[key] is None else r[key]
                               for r in recs], dtype=np.float64)
            mean, lo, hi = mean_interval({arm: values}, reps=reps)[arm]
            cells.append(f"{mean:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]" if len(recs) > 1 else f"{mean:.{digits}f}")
        wall = sum(r["wall_s"] for r in recs) / len(recs)
        rows.append([arm, len(recs), *cells, f"{wall:.0f}"])
    lines.append(markdown_table(["arm", "seeds", *(h for _, h, _ in COLUMNS), "wall per run (s)"], rows))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="MountainCar-v0")
    p.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=40_000)
    p.add_argument("--beta", type=float, default=0.1)
    p.add_argument("--reps", type=int, default=2000)
    p.add_argument("--out", type=Path, default=Path("results/gym-mountaincar"))
    args = p.parse_args(argv)
    if any(s < 0 for s in args.seeds) or args.frames < 1 or not (args.beta >= 0 and math.isfinite(args.beta)):
        p.error("--seeds must be >= 0, --frames >= 1, --beta a finite number >= 0")
    records: dict[str, list[dict]] = {}
    for arm in args.arms:
        for seed in args.seeds:
            path = args.out / "runs" / f"{arm}-s{seed}.json"
            if path.exists():
                rec = json.loads(path.read_text())
            else:
                rec = run_arm(arm, seed, args.env, args.frames, args.beta)
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_json(path, rec, default=str)
            records.setdefault(arm, []).append(rec)
            print(f"{arm} s{seed}: first goal at episode {rec['first_terminated_episode']}, "
                  f"{rec['terminated_episodes']} of {rec['episodes']} at the goal, {rec['wall_s']:.0f} s", flush=True)
    text = (f"# {args.env}, {args.frames} frames, beta {args.beta}\n\n"
            f"`python experiments/gym_study.py --env {args.env} --frames {args.frames} --beta {args.beta} "
            f"--seeds {' '.join(map(str, args.seeds))} --arms {' '.join(args.arms)}`\n\n" + table(records, args.reps))
    atomic_write_bytes(args.out / "table.md", text.encode())
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
