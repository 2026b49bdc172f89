"""What a run needs of this machine's memory: the replay buffer's and the online planner's bytes,
estimated from the config, against the memory available now."""

from __future__ import annotations

from crowdrl.envs.robot_centric import ENTITY_DIM
from crowdrl.sim.crowd import HUMAN_OBS_DIM, ROBOT_OBS_DIM
from crowdrl.training.config import (EVAL_BATCH, ConfigError, RunConfig, counterfactual_on, crowd_range, map_extent,
                                     sees_obstacles)

# Bytes per planned state (robot + N humans: n = N + 1 nodes) when the planner scores it: n·(a + b·n),
# the rise of the resident memory's high-water mark (VmHWM) over one OnlinePlanner.plan call divided by
# the states it expanded (float32, learned predictor, 64 states, depth 2, width 10, N = 10 and N = 64,
# eager attention kernels: the fallback when compiling fails; the compiled ones need less,
# docs/benchmarks.md), rounded up by ~10 %. An upper estimate, not a measurement.
PLANNED_STATE_BYTES = {"sgd3qn": (1450, 500), "sarl": (2700, 12), "lstm_rl": (960, 40), "mp_rgl": (780, 42)}


def acting_batch(run: RunConfig) -> int:
    """The most states the run acts on at once: ``train.num_envs`` (collection),
    ``train.val_episodes`` (validation) or ``min(train.test_episodes, EVAL_BATCH)`` (the test)."""
    t = run.train
    return max(t.num_envs, t.val_episodes, min(t.test_episodes, EVAL_BATCH))


def planned_states(run: RunConfig, batch: int | None = None) -> int:
    """States the online planner expands per step for ``batch`` environments (default
    :func:`acting_batch`): ``width`` per state at each of ``depth`` levels, ``batch·Σ_k width^k``."""
    p = run.planning
    batch = acting_batch(run) if batch is None else batch
    return batch * sum(p.width ** k for k in range(1, p.depth + 1)) if p.enabled else 0


def planner_bytes(run: RunConfig, batch: int | None = None) -> int:
    """Upper estimate of the planner's memory per step (:data:`PLANNED_STATE_BYTES`), which scales
    with the states it expands and, per state, with the crowd (its largest size, ``env.max_humans``)."""
    a, b = PLANNED_STATE_BYTES.get(run.encoder.name, PLANNED_STATE_BYTES["sgd3qn"])  # sgd3qn: the largest
    n = crowd_range(run.env)[1] + 1
    return planned_states(run, batch) * n * (a + b * n)


def transition_bytes(run: RunConfig) -> int:
    """Bytes of one transition in the replay buffer (``RunFacts.replay_keys``): the robot-centric
    state and successor (float32, plus the humans' bool mask when the crowd size varies; among obstacles the
    entity tokens of the humans and the observed edges, ``ENTITY_DIM`` float32 each, with their mask), the
    action, ``index`` and ``steps_to_next_obs`` (int64), the reward (float32), ``done`` and
    ``terminated`` (bool), with the learned predictor the world-frame state and next humans, and with
    ``encoder.lidar`` the scan and the next scan (float32)."""
    low, high = crowd_range(run.env)
    if sees_obstacles(run):
        tokens = high + map_extent(run)[0]
        obs = 4 * (ROBOT_OBS_DIM + ENTITY_DIM * tokens) + tokens
    else:
        obs = 4 * (ROBOT_OBS_DIM + HUMAN_OBS_DIM * high) + (high if low < high else 0)
    out = 2 * obs + 3 * 8 + 4 + 2
    if run.encoder.lidar != "off":
        out += 2 * 4 * run.env.lidar_rays
    if (run.planning.enabled and run.planning.predictor == "learned") or counterfactual_on(run):
        out += 4 * (ROBOT_OBS_DIM + 2 * HUMAN_OBS_DIM * high)
    if counterfactual_on(run) and sees_obstacles(run):  # the episode's map: P polygons of V vertices and their mask
        P, V = map_extent(run)[1]
        out += P * V * (2 * 4 + 1)
    return out


def buffer_bytes(run: RunConfig) -> int:
    """Peak memory of the replay buffer: ``train.buffer_size`` transitions (the storage is allocated
    whole at the first write), and with ``train.save_buffer`` two more copies while a checkpoint is
    serialised (``torch.save`` into memory, then its bytes)."""
    return run.train.buffer_size * transition_bytes(run) * (3 if run.train.save_buffer else 1)


def available_memory(device: str = "cpu") -> int | None:
    """Bytes of memory available now: ``MemAvailable`` of ``/proc/meminfo`` (else free pages by
    ``os.sysconf``) for ``cpu``, the free memory of the CUDA device otherwise; ``None``: unknown."""
    import os

    if device.startswith("cuda"):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[0])
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"


def check_resources(run: RunConfig) -> None:
    """Refuse (:class:`ConfigError`, naming the key) a run whose replay buffer (:func:`buffer_bytes`),
    or whose buffer plus the planner's states per step (:func:`planner_bytes`), would not fit in the
    memory available now (:func:`available_memory`)."""
    free = available_memory(run.device)
    if free is None:
        return
    t, p = run.train, run.planning
    buffer = buffer_bytes(run)
    copies = " (x3 with train.save_buffer=true: the checkpoint is serialised in memory)" if t.save_buffer else ""
    if buffer > free:
        raise ConfigError(f"train.buffer_size: {t.buffer_size} transitions of {transition_bytes(run)} bytes need "
                          f"~{_gib(buffer)}{copies}, more than the {_gib(free)} of memory available on this machine; "
                          f"lower train.buffer_size" + (" or set train.save_buffer=false" if t.save_buffer else ""))
    planner = planner_bytes(run)
    if planner > free - buffer:
        raise ConfigError(f"planning.depth/planning.width: the planner expands {planned_states(run)} states per step "
                          f"(B x sum of width^k, k = 1..depth: width {p.width}, depth {p.depth}, B = {acting_batch(run)}, "
                          f"the largest of train.num_envs, train.val_episodes and min(train.test_episodes, {EVAL_BATCH})) "
                          f"of up to {crowd_range(run.env)[1]} humans: ~{_gib(planner)} per step, more than the "
                          f"{_gib(max(free - buffer, 0))} of memory available on this machine next to the replay buffer; "
                          f"lower planning.depth or planning.width")
