"""Inject the faults a cluster and its users produce into `train.py` and print what happens.

    python experiments/faults.py            # a table: fault, expected, observed, ok
    python experiments/faults.py --json     # {"meta": ..., "rows": [...]}; exit status 1 unless every row is ok

Each fault runs `experiments/train.py` on the smoke budget in a scratch folder (a few minutes in
all on 2 cores), or another command that must refuse in one line (exit 2) and leave nothing
behind. A run killed (SIGKILL or SIGTERM) and resumed with `train.save_buffer=true` must end with
the same weights and test metrics, bit for bit, as the run that was never stopped. The same behaviours are
asserted in `tests/test_reliability.py`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from benchkit import Column, add_json_argument, emit, log

from crowdrl.evaluation.report import eval_file, read_eval_record

ROOT = Path(__file__).resolve().parents[1]
TRAIN = [sys.executable, str(ROOT / "experiments" / "train.py")]
SMOKE = ["preset=smoke", "logger=csv", "logger.render=false"]
ENV = {**os.environ, "WANDB_MODE": "offline"}


def train(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*TRAIN, *args], env=ENV, capture_output=True, text=True, timeout=timeout)


def cli(name: str, *args: str, cwd: Path | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    """Run ``experiments/<name>.py`` with ``args``."""
    return subprocess.run([sys.executable, str(ROOT / "experiments" / f"{name}.py"), *args], env=ENV, cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def one_line_exit_2(proc: subprocess.CompletedProcess, *words: str) -> bool:
    """Exit 2 with one line on stderr holding ``words``, no traceback."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    return proc.returncode == 2 and len(lines) == 1 and all(w in lines[0] for w in words)


# train.py with every atomic write of a checkpoint failing as on a full disk
FULL_DISK = """import errno, os, sys
import crowdrl.training.checkpoint as checkpoint
def full(path, data):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
checkpoint.atomic_write_bytes = full
sys.argv = ["train.py", *sys.argv[1:]]
from crowdrl.cli.train import main
main()
"""


def last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1][:110] if lines else ""


def hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def status(folder: Path) -> str:
    path = folder / "status.json"
    return json.loads(path.read_text())["state"] if path.exists() else "(none)"


def nothing_overwritten(scratch: Path, done: Path, record: Callable[[str, str, str, bool], None]) -> None:
    """Issue 52: a command writes only into a folder it created or one carrying its own marker, never over
    a record it did not write in this call; each refusal is one line, exit 2, everything as it was."""
    mine = scratch / "users-table"
    mine.mkdir()
    (mine / "table.md").write_text("mine")
    proc = cli("reproduce", "variants=[egreedy]", "seeds=[0]", "episodes=2", f"out={mine}")
    record("reproduce.py out=<the user's folder with table.md>", "exit 2 naming out, table.md unchanged",
           f"exit {proc.returncode}: {last_line(proc.stderr)}",
           one_line_exit_2(proc, "out:", "no manifest.json") and [p.name for p in mine.iterdir()] == ["table.md"]
           and (mine / "table.md").read_text() == "mine")
    where = scratch / "cli-reproduce-out-empty"
    where.mkdir()
    proc = cli("reproduce", "variants=[egreedy]", "seeds=[0]", "episodes=2", "out=", cwd=where)
    record("reproduce.py out=''", "exit 2 naming out, nothing written", f"exit {proc.returncode}: {last_line(proc.stderr)}",
           one_line_exit_2(proc, "out: is empty") and not any(where.iterdir()))
    run = scratch / "evaluated-run"
    shutil.copytree(done, run)
    before = hashes(run)
    proc = cli("evaluate", f"checkpoint={run}", "eval.episodes=2", f"hydra.run.dir={run}")
    record("evaluate.py checkpoint=<run> hydra.run.dir=<run>", "exit 2 naming the folder, its eval.json unchanged",
           f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}",
           one_line_exit_2(proc, "hydra.run.dir:", str(run)) and hashes(run) == before)
    for i, manifest in enumerate(("garbage", "[]")):
        out = scratch / f"manifest-{i}"
        out.mkdir()
        (out / "manifest.json").write_text(manifest)
        proc = cli("reproduce", "variants=[egreedy]", "seeds=[0]", "episodes=2", f"out={out}")
        record(f"reproduce.py rerun, manifest.json {manifest!r}", "exit 2 naming manifest.json",
               f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}",
               one_line_exit_2(proc, "manifest.json") and (out / "manifest.json").read_text() == manifest)
    file = scratch / "a-file"
    file.write_text("mine")
    for name, args in (("train", [*SMOKE, f"hydra.run.dir={file}"]), ("evaluate", ["policy=orca", f"hydra.run.dir={file}"]),
                       ("reproduce", ["variants=[egreedy]", "seeds=[0]", f"out={file}"])):
        proc = cli(name, *args)
        record(f"{name}.py {args[-1].split('=')[0]}=<a file>", "exit 2 naming the path, the file unchanged",
               f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}",
               one_line_exit_2(proc, str(file), "is a file, not a folder") and file.read_text() == "mine")
    where = scratch / "cli-train-sweep"
    where.mkdir()
    proc = cli("train", "-m", *SMOKE, "seed=abc,0", cwd=where)
    record("train.py -m seed=abc,0", "exit 2 naming seed, no sweep folder", f"exit {proc.returncode}: {last_line(proc.stderr)}",
           one_line_exit_2(proc, "seed:") and not any(where.iterdir()))


def issue_52_defects(scratch: Path, record: Callable[[str, str, str, bool], None]) -> None:
    """Issue 52, D1-D15: values refused at start naming the key (no folder), SIGTERM to evaluate.py handled
    as Ctrl-C, a combination that crashed at its first update now trains, a hand-edited record refused, the
    Gymnasium face's bad options and actions refused."""
    for i, (name, args, words) in enumerate((("train", [*SMOKE, "env=room", "env.room_pillars=1000"],
                                               ["env.room_pillars (1000)"]),
                              ("train", [*SMOKE, "env=room", "env.room_pillar_min=5", "env.room_pillar_max=20"],
                               ["env.room_pillars"]),
                              ("train", [*SMOKE, "env=room", "env.num_humans=64"], ["env.num_humans (64)", "at most 18"]),
                              ("train", [*SMOKE, "env=corridor", "env.num_humans=19"], ["env.num_humans (19)", "at most 14"]),
                              ("train", [*SMOKE, "env=doorway", "env.num_humans=64"], ["env.num_humans (64)", "at most 14"]),
                              ("evaluate", ["policy=orca", "env=corridor", "eval.num_humans=19"],
                               ["num_humans (19)", "at most 14"]))):
        where = scratch / f"cli-d1-{i}"
        where.mkdir()
        proc = cli(name, *args, cwd=where)
        shown = " ".join(a for a in args if a not in SMOKE)
        record(f"{name}.py {shown}", "exit 2 at start naming the key and the largest crowd, no folder",
               f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}",
               one_line_exit_2(proc, *words) and not any(where.iterdir()))
    gymnasium_face(record)
    for override, words in (("env.lidar_rays=100000000", ["env.lidar_rays", "0..1024"]),
                            ("train.q_layer_norm=2", ["train.q_layer_norm: must be true or false, got 2"])):
        folder = scratch / override.replace("=", "-")
        proc = train(*SMOKE, override, f"hydra.run.dir={folder}")
        record(f"train.py {override}", "exit 2 at start naming the key, no run folder",
               f"exit {proc.returncode}: {last_line(proc.stderr)}", one_line_exit_2(proc, *words) and not folder.exists())
    folder = scratch / "eval-sigterm"
    proc = subprocess.Popen([sys.executable, str(ROOT / "experiments" / "evaluate.py"), "policy=orca",
                             "eval.episodes=3000", "eval.record_episode=null", f"hydra.run.dir={folder}"], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None and not folder.exists():
        time.sleep(0.1)
    time.sleep(1.0)  # into the evaluation
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    record("SIGTERM during evaluate.py", "exit 130 as Ctrl-C, the eval folder it made removed",
           f"exit {proc.returncode}: {last_line(err)}, folder {'left' if folder.exists() else 'gone'}",
           proc.returncode == 130 and "interrupted" in err and not folder.exists())
    folder = scratch / "re3-merged-n2"
    proc = train(*SMOKE, "exploration=re3", "train.counterfactual.mode=merged", "train.n_step=2",
                 f"hydra.run.dir={folder}")
    record("train.py exploration=re3 train.counterfactual.mode=merged train.n_step=2",
           "trains (was KeyError one_step_next at the first update)", f"exit {proc.returncode}, status {status(folder)}",
           proc.returncode == 0 and status(folder) == "completed")
    out = scratch / "reproduce-edited"
    args = ["variants=[egreedy]", "seeds=[0]", "episodes=4", "budget=smoke", f"out={out}"]
    first = cli("reproduce", *args)
    edited = out / "runs" / "egreedy-s0" / "eval-circle" / "eval.json"
    if first.returncode == 0 and edited.exists():
        table = (out / "table.md").read_bytes()
        rec = read_eval_record(edited)
        edited.write_text(json.dumps(eval_file([{**rec, "success_rate": 0.99 if rec["success_rate"] != 0.99 else 0.5}])))
        proc = cli("reproduce", *args)
        ok = one_line_exit_2(proc, str(edited), "success_rate", "summary.json") and (out / "table.md").read_bytes() == table
        observed = f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}"
    else:
        ok, observed = False, f"the first reproduce.py failed: exit {first.returncode}: {last_line(first.stderr)}"
    record("reproduce.py rerun, a run's eval-circle/eval.json hand-edited (in range)",
           "exit 2 naming the file and its summary.json, table.md unchanged", observed, ok)


def gymnasium_face(record: Callable[[str, str, str, bool], None]) -> None:
    """Issue 52, D11-D13: the Gymnasium env refuses an episode id past int64, unknown reset options and a
    complex (or boolean) holonomic velocity, naming them, in one ValueError; the ONNX example a non-finite
    state, and pads a view with no human."""
    import gymnasium as gym
    import numpy as np

    import crowdrl  # noqa: F401  (registers the ids)

    def refused(call: Callable[[], object], *words: str) -> tuple[bool, str]:
        try:
            call()
        except ValueError as exc:
            return all(w in str(exc) for w in words), f"ValueError: {str(exc)[:80]}"
        except Exception as exc:  # noqa: BLE001  (any other error is the defect)
            return False, f"{type(exc).__name__}: {str(exc)[:80]}"
        return False, "accepted"

    env = gym.make("crowdrl/CircleCrossing-v0").unwrapped
    for options, words in (({"episode_id": 2**63}, ["options['episode_id']", "0..2**63-1"]),
                           ({"episod_id": 3}, ["unknown key(s) 'episod_id'"]), ("junk", ["options must be"]),
                           ([1, 2], ["options must be"])):
        ok, observed = refused(lambda: env.reset(seed=0, options=options), *words)
        record(f"Gymnasium reset(options={options!r})", "ValueError naming the option", observed, ok)
    hol = gym.make("crowdrl/CircleCrossing-v0", robot_kinematics="holonomic").unwrapped
    hol.reset(seed=0)
    ok, observed = refused(lambda: hol.step(np.array([1 + 1j, 0])), "finite real velocity")
    record("holonomic Gymnasium step(np.array([1+1j, 0]))", "ValueError: a finite real velocity", observed, ok)
    # D13: the ONNX example's inputs (onnxruntime and numpy only)
    from crowdrl import onnx_example

    robot = np.array([0.0, -4.0, np.nan, 0.5, 0.3, 0.0, 4.0, 1.0, np.pi / 2])
    humans = np.array([[0.3, -2.5, 0.0, -0.8, 0.3]])
    ok, observed = refused(lambda: onnx_example.observation(robot, humans), "robot:", "not finite")
    record("onnx_example.observation, a NaN robot state", "ValueError naming the field", observed, ok)
    robot[2] = 0.0
    try:
        alone = onnx_example.observation(robot, np.zeros((0, 5)))
        ok, observed = not bool(alone["humans_mask"].any()), f"one absent row {alone['humans_rc'].shape}"
    except Exception as exc:  # noqa: BLE001  (the defect: onnxruntime's Reshape error downstream, or any error)
        ok, observed = False, f"{type(exc).__name__}: {str(exc)[:80]}"
    record("onnx_example.observation, no human in view", "one absent row (humans_mask false)", observed, ok)


def scalar_rows(folder: Path) -> list[dict]:
    """The logged rows of a run, its wall-clock ``time/`` columns aside."""
    return [{k: v for k, v in json.loads(line).items() if not k.startswith("time/")}
            for line in (folder / "scalars.jsonl").read_text().splitlines()]


def kill_when_checkpointed(args: list[str], folder: Path, sig: signal.Signals, at_frames: int) -> int:
    """Start a run, send ``sig`` once its last.pt holds ``at_frames`` frames or more; the frames it held."""
    from crowdrl.training.checkpoint import CheckpointError, load_checkpoint

    proc = subprocess.Popen([*TRAIN, *args, f"hydra.run.dir={folder}"], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = folder / "checkpoints" / "last.pt"
    deadline, frames = time.time() + 300, 0
    while time.time() < deadline and proc.poll() is None:
        try:
            frames = load_checkpoint(last)["counters"]["frames"] if last.exists() else 0
        except CheckpointError:  # written atomically, but a read can race the rename
            frames = 0
        if frames >= at_frames:
            break
        time.sleep(0.05)
    proc.send_signal(sig)
    proc.wait(timeout=300)
    return frames


def same_result(a: Path, b: Path) -> tuple[bool, bool]:
    """(final weights bit-identical, test metrics identical) of two finished run folders."""
    import torch

    from crowdrl.training.checkpoint import load_checkpoint

    wa, wb = (load_checkpoint(f / "checkpoints" / "last.pt")["loss"] for f in (a, b))
    weights = wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    ma, mb = (read_eval_record(f / "eval.json") for f in (a, b))
    return weights, ma == mb


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_json_argument(p)
    opts = p.parse_args(argv)
    rows: list[dict] = []
    scratch = Path(tempfile.mkdtemp(prefix="crowdrl-faults-"))

    def record(fault: str, expected: str, observed: str, ok: bool) -> None:
        rows.append({"fault": fault, "expected": expected, "observed": observed, "ok": bool(ok)})
        log(f"{fault}: {'ok' if ok else 'NOT OK'}")

    for override in ("train.lr=inf", "exploration.beta=nan", "device=cuda", "train.batch_size=5000"):
        folder = scratch / override.replace("=", "-")
        proc = train(*SMOKE, override, f"hydra.run.dir={folder}")
        record(override, "exit 2 at start naming the key, no run folder",
               f"exit {proc.returncode}: {last_line(proc.stderr)}",
               proc.returncode == 2 and override.split("=")[0] in proc.stderr and not (folder / "config.yaml").exists())

    blown = scratch / "nan"
    proc = train(*SMOKE, "train.lr=1e30", f"hydra.run.dir={blown}")
    record("train.lr=1e30 (weights blow up)", "exit 1, status failed, no eval.json",
           f"exit {proc.returncode}, status {status(blown)}, eval.json {(blown / 'eval.json').exists()}",
           proc.returncode == 1 and status(blown) == "failed" and not (blown / "eval.json").exists())

    done = scratch / "done"
    train(*SMOKE, f"hydra.run.dir={done}")
    cut = scratch / "cut"
    shutil.copytree(done, cut)
    last = cut / "checkpoints" / "last.pt"
    last.write_bytes(last.read_bytes()[:5000])
    before = hashes(cut)
    proc = train(f"resume={cut}")
    record("resume from a truncated last.pt", "exit 2, folder byte for byte unchanged",
           f"exit {proc.returncode}, unchanged {hashes(cut) == before}", proc.returncode == 2 and hashes(cut) == before)

    proc = train(f"resume={done}", "seed=5")
    record("resume with a conflicting override (seed=5)", "exit 2 naming the override",
           f"exit {proc.returncode}: {last_line(proc.stderr)}", proc.returncode == 2 and "seed=5" in proc.stderr)

    # one clear line, exit 2, nothing left behind (issue 40)
    for name, args, words in (("train", ["seed=abc"], ["seed:"]), ("train", ["resume="], ["resume:"]),
                              ("evaluate", ["env=mars"], ["env/mars"]),
                              ("evaluate", ["policy=orca", "eval.episodes=1000000000"], ["eval.episodes"]),
                              ("demo", ["train.num_envs=abc"], ["train.num_envs"]),
                              ("export", [f"checkpoint={done}", "check=maybe"], ["check:"])):
        where = scratch / f"cli-{name}-{len(rows)}"
        where.mkdir()
        proc = cli(name, *args, cwd=where)
        record(f"{name}.py {' '.join(a.replace(str(done), '<run>') for a in args)}",
               "exit 2, one line naming the key, no folder", f"exit {proc.returncode}: {last_line(proc.stderr)}",
               one_line_exit_2(proc, *words) and not any(where.iterdir()))
    existing = scratch / "existing.onnx"
    existing.write_text("mine")
    proc = cli("export", f"checkpoint={done}", f"out={existing}")
    record("export.py out=<an existing file>", "exit 2 naming out, file unchanged",
           f"exit {proc.returncode}: {last_line(proc.stderr)}",
           one_line_exit_2(proc, "out:", "overwrite=true") and existing.read_text() == "mine")
    text = scratch / "notes.pt"
    text.write_text("hello\n")
    proc = cli("evaluate", f"checkpoint={text}", f"hydra.run.dir={scratch / 'eval-text'}")
    record("evaluate.py checkpoint=<a text file>", "exit 2, 'not a torch file'", f"exit {proc.returncode}: "
           f"{last_line(proc.stderr)}", one_line_exit_2(proc, "not a torch file") and not (scratch / "eval-text").exists())
    nothing_overwritten(scratch, done, record)
    issue_52_defects(scratch, record)
    from omegaconf import OmegaConf

    humans = int(OmegaConf.load(done / "config.yaml").env.num_humans)
    for damage, words in (("unknown key", ["foo: Key 'foo'"]), ("_target_", ["_target_"]),
                          ("edited env.num_humans", [f"env.num_humans: {humans + 1} here, {humans} in the checkpoint"])):
        folder = scratch / f"config-{damage.replace(' ', '-')}"
        shutil.copytree(done, folder)
        (folder / "summary.json").unlink()  # not complete: the resume reads its checkpoint
        config = (folder / "config.yaml").read_text()
        if damage == "unknown key":
            config += "foo: 1\n"
        elif damage == "_target_":
            config = "_target_: os.system\n" + config
        else:
            edited = OmegaConf.create(config)
            edited.env.num_humans = humans + 1
            config = OmegaConf.to_yaml(edited)
        (folder / "config.yaml").write_text(config)
        before = hashes(folder)
        proc = train(f"resume={folder}")
        record(f"resume, config.yaml with {damage}", "exit 2 naming the key, folder unchanged",
               f"exit {proc.returncode}: {last_line(proc.stderr)[:90]}",
               one_line_exit_2(proc, *words) and hashes(folder) == before)
    disk = scratch / "full-disk"
    proc = subprocess.run([sys.executable, "-c", FULL_DISK, *SMOKE, f"hydra.run.dir={disk}"], env=ENV,
                          capture_output=True, text=True, timeout=600)
    record("disk full (ENOSPC) at the first checkpoint", "exit 2 naming last.pt, status failed, no temporary",
           f"exit {proc.returncode}, status {status(disk)}: {last_line(proc.stderr)[:70]}",
           one_line_exit_2(proc, "last.pt", "ENOSPC", "resume=") and status(disk) == "failed"
           and not list(disk.rglob("*.tmp")))

    term = scratch / "sigterm"
    proc = subprocess.Popen([*TRAIN, *SMOKE, "train.total_frames=640", "train.checkpoint_every_frames=100000",
                             f"hydra.run.dir={term}"], env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if (term / "scalars.jsonl").exists() and '"kind": "val"' in (term / "scalars.jsonl").read_text():
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=300)
    record("SIGTERM during training", "exit 130, status interrupted, last.pt written",
           f"exit {code}, status {status(term)}, last.pt {(term / 'checkpoints' / 'last.pt').exists()}",
           code == 130 and status(term) == "interrupted" and (term / "checkpoints" / "last.pt").exists())

    exact = [*SMOKE, "train.total_frames=512", "train.save_buffer=true"]
    ref = scratch / "uninterrupted"
    train(*exact, f"hydra.run.dir={ref}")
    for sig in (signal.SIGKILL, signal.SIGTERM):
        folder = scratch / f"killed-{sig.name}"
        frames = kill_when_checkpointed(exact, folder, sig, at_frames=192)
        # what a kill during the write of last.pt leaves (a dead process's temporary, buffer-sized)
        dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
        stale = folder / "checkpoints" / f".last.pt.{int(dead.stdout)}.0123456789ab.tmp"
        stale.parent.mkdir(parents=True, exist_ok=True)  # a run killed before its first checkpoint has none
        stale.write_bytes(b"\0" * 4096)
        proc = train(f"resume={folder}")
        same_weights, same_metrics = same_result(ref, folder)
        record(f"{sig.name} at frame >= {frames}, resume (save_buffer=true)",
               "bit-identical final weights and test metrics, no temporary left",
               f"exit {proc.returncode}, weights {'same' if same_weights else 'DIFFER'}, "
               f"metrics {'same' if same_metrics else 'DIFFER'}, temporary {'left' if stale.exists() else 'gone'}",
               proc.returncode == 0 and same_weights and same_metrics and not stale.exists())

    # issue 52 D3: with counterfactual experience, every logged column (its losses and scalars too) survives a kill
    cf = [*exact, "train.counterfactual.mode=second_update"]
    ref = scratch / "uninterrupted-counterfactual"
    train(*cf, f"hydra.run.dir={ref}")
    folder = scratch / "killed-counterfactual"
    frames = kill_when_checkpointed(cf, folder, signal.SIGKILL, at_frames=192)
    proc = train(f"resume={folder}")
    same_weights, same_metrics = same_result(ref, folder)
    rows_equal = scalar_rows(ref) == scalar_rows(folder)
    record(f"SIGKILL at frame >= {frames} with counterfactual experience, resume",
           "bit-identical weights, test metrics and every logged column but time/",
           f"exit {proc.returncode}, weights {'same' if same_weights else 'DIFFER'}, metrics "
           f"{'same' if same_metrics else 'DIFFER'}, rows {'same' if rows_equal else 'DIFFER'}",
           proc.returncode == 0 and same_weights and same_metrics and rows_equal)

    shutil.rmtree(scratch, ignore_errors=True)
    emit(rows, columns=[Column("fault"), Column("expected"), Column("ok"), Column("observed")], as_json=opts.json,
         meta={"all_ok": all(r["ok"] for r in rows)},
         title="Faults injected into train.py (smoke budget): what was expected, what happened")
    return rows


if __name__ == "__main__":
    rows = main(sys.argv[1:])
    raise SystemExit(0 if all(r["ok"] for r in rows) else 1)
