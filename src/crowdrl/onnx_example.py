"""Run an exported crowdrl policy with numpy and onnxruntime only (no torch, no crowdrl).

    crowdrl-export checkpoint=runs/<folder> out=policy.onnx    # or python experiments/export.py ...
    python path/to/crowdrl/onnx_example.py policy.onnx        # or python experiments/onnx_example.py ...

This file imports nothing of crowdrl and is run by its path (``crowdrl-export`` prints it), never
imported through the package: copy it onto the robot beside the model.

Builds the observation of one robot among a few humans from world-frame states and runs the model: an
exported online planner (``crowdrl.policy`` ``planner``, every shipped agent) reads the world-frame states
themselves (:func:`world_observation`); a greedy Q model reads them in the robot's goal-aligned frame (the
transform of ``crowdrl.envs.robot_centric.robot_centric``, written again in numpy below:
:func:`observation`). Prints the action, its command (speed, rotation) and the world-frame velocity the
robot then drives at. Copy :func:`world_observation` or :func:`observation` into a robot's code.
"""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np


def robot_centric(robot: np.ndarray, humans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World frame -> the robot's frame (origin at the robot, x towards its goal).

    ``robot [..., 9]`` = (px, py, vx, vy, radius, gx, gy, v_pref, heading), ``humans [..., N, 5]`` =
    (px, py, vx, vy, radius) -> ``robot_rc [..., 9]`` = (0, 0, vx', vy', radius, goal distance, 0,
    v_pref, heading - goal direction wrapped to [-pi, pi)) and ``humans_rc [..., N, 5]`` = (px', py',
    vx', vy', radius + robot radius), primes being rotated by minus the goal direction.
    """
    px, py, vx, vy, r, gx, gy, v_pref, theta = np.moveaxis(robot, -1, 0)
    dgx, dgy = gx - px, gy - py
    rot = np.arctan2(dgy, dgx)
    c, s = np.cos(rot), np.sin(rot)
    zero = np.zeros_like(px)
    heading = np.remainder(theta - rot + math.pi, 2 * math.pi) - math.pi
    robot_rc = np.stack((zero, zero, vx * c + vy * s, -vx * s + vy * c, r, np.sqrt(dgx * dgx + dgy * dgy), zero,
                         v_pref, heading), axis=-1)
    c, s = c[..., None], s[..., None]
    hx, hy = humans[..., 0] - px[..., None], humans[..., 1] - py[..., None]
    hvx, hvy = humans[..., 2], humans[..., 3]
    humans_rc = np.stack((hx * c + hy * s, -hx * s + hy * c, hvx * c + hvy * s, -hvx * s + hvy * c,
                          humans[..., 4] + r[..., None]), axis=-1)
    return robot_rc, humans_rc


ROBOT_FIELDS = ("px", "py", "vx", "vy", "radius", "gx", "gy", "v_pref", "heading")
HUMAN_FIELDS = ("px", "py", "vx", "vy", "radius")


def check_states(robot: np.ndarray, humans: np.ndarray) -> None:
    """``ValueError`` naming the fields (and the humans' rows) of ``robot [9]`` / ``humans [n, 5]`` that
    are NaN or infinite: the model would turn them into NaN Q values and an arbitrary action."""
    if robot.shape != (len(ROBOT_FIELDS),):
        raise ValueError(f"robot: must hold the {len(ROBOT_FIELDS)} values {', '.join(ROBOT_FIELDS)}, got shape {robot.shape}")
    bad = [name for name, ok in zip(ROBOT_FIELDS, np.isfinite(robot)) if not ok]
    if bad:
        raise ValueError(f"robot: {', '.join(bad)} not finite (NaN or inf): {robot.tolist()}; give finite states")
    rows = [i for i, ok in enumerate(np.isfinite(humans).all(axis=1)) if not ok]
    if rows:
        i = rows[0]
        bad = [name for name, ok in zip(HUMAN_FIELDS, np.isfinite(humans[i])) if not ok]
        raise ValueError(f"humans: row(s) {rows} not finite (NaN or inf; row {i}: {', '.join(bad)}); give finite "
                         "states, or leave out a human the robot cannot see")


def _checked(robot: np.ndarray, humans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``robot [9]`` and ``humans [n, 5]`` as float64 arrays, their shape and finiteness checked."""
    robot, humans = np.asarray(robot, np.float64), np.asarray(humans, np.float64)
    if humans.size % len(HUMAN_FIELDS):
        raise ValueError(f"humans: must be rows of the {len(HUMAN_FIELDS)} values {', '.join(HUMAN_FIELDS)}, "
                         f"got shape {humans.shape}")
    humans = humans.reshape(-1, len(HUMAN_FIELDS))
    check_states(robot, humans)
    return robot, humans


def _padded(rows: np.ndarray, slots: int | None) -> tuple[np.ndarray, np.ndarray]:
    """``rows [n, 5]`` padded with absent rows to ``slots`` (default ``max(n, 1)``), and the presence mask."""
    n = rows.shape[0]
    slots = max(n, 1) if slots is None else slots
    if n > slots:
        raise ValueError(f"the model takes at most {slots} humans, got {n}")
    padded = np.zeros((slots, 5))
    padded[:n] = rows
    return padded[None].astype(np.float32), (np.arange(slots) < n)[None]


def observation(robot: np.ndarray, humans: np.ndarray, slots: int | None = None) -> dict[str, np.ndarray]:
    """The model's inputs for one robot: ``robot [9]`` and ``humans [n, 5]`` in the world frame,
    padded with absent rows (``humans_mask`` False) to ``slots`` rows when the model fixes N. No human
    in view (``n = 0``): one absent row (the models are padding-invariant and need a row to run).
    Non-finite states are refused (:func:`check_states`)."""
    robot, humans = _checked(robot, humans)
    robot_rc, humans_rc = robot_centric(robot, humans)
    padded, mask = _padded(humans_rc, slots)
    return {"robot_rc": robot_rc[None].astype(np.float32), "humans_rc": padded, "humans_mask": mask}


def world_observation(robot: np.ndarray, humans: np.ndarray, slots: int | None = None,
                      walls: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The inputs of an exported planner for one robot: ``robot [9]`` and ``humans [n, 5]`` in the world frame
    as they are (``robot``, ``humans``), padded with absent rows (``humans_mask`` False) to ``slots`` rows when
    the model fixes N; no human in view: one absent row. Non-finite states are refused (:func:`check_states`).
    ``walls [k, 4]`` (ax, ay, bx, by per edge, world frame; a planner trained among obstacles takes them, nearest
    first): ``obstacles`` and ``obstacles_mask``; no edge in view: one absent row."""
    robot, humans = _checked(robot, humans)
    padded, mask = _padded(humans, slots)
    feeds = {"robot": robot[None].astype(np.float32), "humans": padded, "humans_mask": mask}
    if walls is not None:
        walls = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        if not np.isfinite(walls).all():
            raise ValueError("walls: every edge coordinate must be finite")
        present = len(walls) > 0
        feeds["obstacles"] = (walls if present else np.zeros((1, 4)))[None].astype(np.float32)
        feeds["obstacles_mask"] = np.full((1, max(len(walls), 1)), present)
    return feeds


FORMAT_VERSION = 2  # the newest crowdrl.format_version this example reads (none: 1, a greedy Q model)


def format_version_of(meta: dict[str, str]) -> int:
    """The model's ``crowdrl.format_version`` (1 when absent); ``ValueError`` naming the field when it is not a
    version number or is newer than :data:`FORMAT_VERSION`."""
    text = meta.get("crowdrl.format_version", "1")
    if not text.isdigit():
        raise ValueError(f"metadata crowdrl.format_version: not a version number: {text!r}")
    if int(text) > FORMAT_VERSION:
        raise ValueError(f"metadata crowdrl.format_version: {text} is newer than this example reads "
                         f"({FORMAT_VERSION}); use the onnx_example.py of the crowdrl that wrote the model")
    return int(text)


def time_step_of(meta: dict[str, str]) -> float:
    """The model's ``crowdrl.time_step`` metadata (seconds per step; 0.25 when absent); ``ValueError``
    naming the field unless it is a finite number > 0."""
    text = meta.get("crowdrl.time_step", "0.25")
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"metadata crowdrl.time_step: must be a finite number of seconds > 0, got {text!r}")
    return value


def main(argv: list[str] | None = None) -> dict:
    import onnxruntime

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the .onnx file written by crowdrl-export (experiments/export.py)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = p.parse_args(argv)
    if not os.path.isfile(args.model):
        p.error(f"model: no file at {args.model} (write one with crowdrl-export)")
    try:
        session = onnxruntime.InferenceSession(args.model, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's errors: not a model, or a damaged one
        first = next((line for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        p.error(f"model: {args.model} is not an ONNX model onnxruntime can load ({first[:200]})")
    meta = session.get_modelmeta().custom_metadata_map
    try:
        format_version_of(meta)
        time_step = time_step_of(meta)
    except ValueError as exc:
        p.error(f"model: {args.model}: {exc} (a model written by crowdrl-export holds it)")
    shapes = {i.name: i.shape for i in session.get_inputs()}
    planner = "humans" in shapes  # the exported online planner reads the world-frame states
    rows = "humans" if planner else "humans_rc"
    if rows not in shapes:
        p.error(f"model: {args.model} takes {sorted(shapes)} (a greedy Q policy trained among obstacles reads entity "
                "tokens); this example builds the inputs of a planner (robot, humans, humans_mask, and obstacles, "
                "obstacles_mask when it reads walls) and of an open-space greedy Q model (robot_rc, humans_rc, "
                "humans_mask) only (docs/export.md)")
    n_axis = shapes[rows][1]
    slots = n_axis if isinstance(n_axis, int) else None  # an int: the model fixes N (pad); a name: free

    # the robot at (0, -4) heading north towards its goal (0, 4), driving at 0.5 m/s; three humans
    robot = np.array([0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, math.pi / 2])
    humans = np.array([[0.3, -2.5, 0.0, -0.8, 0.3],    # coming straight at it
                       [-1.5, -1.0, 0.6, 0.0, 0.3],    # crossing from the left
                       [2.0, 1.0, 0.0, 0.0, 0.3]])     # standing
    # a wall across the way at y = -1 with a 2 m gap at x = 0 (edges ax, ay, bx, by), for a planner that reads walls
    walls = np.array([[-5.0, -1.0, -1.0, -1.0], [1.0, -1.0, 5.0, -1.0]]) if "obstacles" in shapes else None
    feeds = world_observation(robot, humans, slots, walls) if planner else observation(robot, humans, slots)
    q, action, command = session.run(["q_values", "action", "command"], feeds)
    a = int(action[0])
    speed, rotation = (float(x) for x in command[0])
    heading = robot[8] + rotation  # the unicycle turns first, then drives straight for one step
    result = {"action": a, "q": float(q[0, a]), "speed": speed, "rotation": rotation,
              "angular_rate": rotation / time_step,
              "velocity_world": [speed * math.cos(heading), speed * math.sin(heading)],
              "policy": "planner" if planner else "greedy_q", "planning": meta.get("crowdrl.planning", "unknown")}
    if args.json:
        print(json.dumps(result))
    else:
        chooser = "planner" if planner else "greedy"
        print(f"{chooser} action {a} (Q {result['q']:.4f}): speed {speed:.3f} m/s, rotation {rotation:+.4f} rad "
              f"({result['angular_rate']:+.3f} rad/s over the step)")
        print(f"world-frame velocity: vx {result['velocity_world'][0]:+.3f}, vy {result['velocity_world'][1]:+.3f} m/s")
        if not result["planning"].startswith(("off", "on")):
            print(f"note: planning {result['planning']}")
    return result


if __name__ == "__main__":
    main()
