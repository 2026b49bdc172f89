"""Makes orca_no_obstacle_baseline.npz: orca_solve's outputs at commit c377921 (before obstacle ORCA) on
random padded scenes, the fixture that keeps the no-obstacle path bit-identical (run from the repo root:
``PYTHONPATH=experiments python tests/data/make_orca_no_obstacle_baseline.py``)."""
import numpy as np
import torch
from crowdrl.sim.orca import OrcaParams, orca_solve
from crowdrl_testing import KINDS, padded_batch, random_scene
torch.set_num_threads(1)
out = {}
gen = np.random.default_rng(20240)
for kind in KINDS:
    scenes = [random_scene(gen, kind) for _ in range(60)]
    batch, mask = padded_batch(scenes, torch.float32)
    for k, v in batch.items():
        out[f"{kind}/in/{k}"] = v.numpy()
    out[f"{kind}/in/mask"] = mask.numpy()
    for dt in (torch.float32, torch.float64):
        for use_mask in (True, False):
            if not use_mask and kind != "crowd":
                continue
            sol = orca_solve(**{k: v.to(dt) for k, v in batch.items()}, mask=mask if use_mask else None,
                             params=OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0))
            tag = f"{kind}/{str(dt)[6:]}_{'mask' if use_mask else 'nomask'}"
            out[f"{tag}/velocities"] = sol.velocities.numpy()
            out[f"{tag}/lp_infeasible"] = sol.lp_infeasible.numpy()
            out[f"{tag}/num_neighbors"] = sol.num_neighbors.numpy()
np.savez_compressed("tests/data/orca_no_obstacle_baseline.npz", **out)
print(len(out), sorted(out)[:12])
