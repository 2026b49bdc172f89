"""Export a trained checkpoint's acting policy as an ONNX model, for robots (Hydra entry point:
``crowdrl-export``, ``python -m crowdrl.cli.export`` or ``python experiments/export.py`` in a checkout;
needs the ``export`` extra: onnx, onnxruntime).

    python experiments/export.py checkpoint=runs/<folder> out=policy.onnx      # its checkpoints/best.pt
    python experiments/export.py checkpoint=path/to/best.pt out=models/policy.onnx opset=17
    python experiments/export.py checkpoint=runs/<folder> out=greedy.onnx planning_depth=0   # greedy Q alone

A checkpoint that acts with online planning exports its planner whole (Q network, crowd predictor,
look-ahead; depth, width and safety horizon the checkpoint's or ``planning_*``'s); ``planning_depth=0``
exports its greedy Q policy alone, which acts differently (printed, and labelled in the metadata).
Inputs, outputs and metadata: ``docs/export.md`` and :mod:`crowdrl.export`. ``crowdrl/onnx_example.py``
(installed with the package; ``experiments/onnx_example.py`` in a checkout) runs the model with numpy and
onnxruntime alone; ``evaluate.py checkpoint=<file>.onnx`` evaluates it on the test cases. An existing
``out`` file is replaced only with ``overwrite=true``. A bad argument (checkpoint, out, format, opset,
check, overwrite, planning_*) exits with code 2 and a message naming it; nothing is written then.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NoReturn

from omegaconf import DictConfig

from crowdrl.cli import exit_with_error, hydra_command
from crowdrl.resources import config_dir, onnx_example

# the check runs the torch policy a few times: compiling SG-D3QN's pairwise kernel for that would
# cost more than it saves (up to a minute on first use)
os.environ.setdefault("CROWDRL_PAIRWISE", "eager")

CONF_DIR = str(config_dir())


def fail(message: str) -> NoReturn:
    exit_with_error("export", message)


def _register_schema() -> None:
    """The typed schema of ``conf/export.yaml`` (its defaults list's ``export_schema``): Hydra refuses
    an unknown key or a value of the wrong type (``opset=abc``, ``check=maybe``), naming it."""
    from hydra.core.config_store import ConfigStore

    from crowdrl.cli.schemas import ExportConfig

    ConfigStore.instance().store(name="export_schema", node=ExportConfig)


_register_schema()


def allowed_hint(key: str = "") -> str:
    """The keys export.py reads (its schema's), for its messages."""
    from crowdrl.cli.schemas import ExportConfig
    from crowdrl.schema import allowed_keys

    return ", ".join(allowed_keys(ExportConfig))


@hydra_command("export", "export", allowed=allowed_hint)
def main(cfg: DictConfig) -> dict:
    from crowdrl.cli.schemas import ExportConfig
    from crowdrl.export import FORMATS
    from crowdrl.schema import SchemaError, read_typed

    try:  # a key added with + that nothing reads (Hydra refuses other unknown keys and wrong types)
        c = read_typed(ExportConfig, cfg, reader="export.py", allowed=allowed_hint())
    except SchemaError as exc:
        fail(str(exc))
    if c.format not in FORMATS:
        fail(f"format: got {c.format!r}; allowed: {', '.join(FORMATS)}")
    if not c.checkpoint:
        fail("checkpoint: required (a run folder or a .pt file), e.g. checkpoint=runs/<folder>")
    if not c.out:
        fail("out: required (the .onnx file to write), e.g. out=policy.onnx")
    if not 14 <= c.opset <= 20:
        fail(f"opset: got {c.opset!r}; an integer in 14..20")
    if Path(c.out).exists() and not c.overwrite:
        fail(f"out: {c.out} exists; pass overwrite=true to replace it, or choose another out=")

    from crowdrl.export import export_onnx
    from crowdrl.training import CheckpointError

    try:
        info = export_onnx(c.checkpoint, c.out, opset=c.opset, check=c.check,
                           planning={"depth": c.planning_depth, "width": c.planning_width,
                                     "safety_horizon": c.planning_safety_horizon,
                                     "progress_bias": c.planning_progress_bias})
    except CheckpointError as exc:
        fail(f"checkpoint: {exc}")
    except ValueError as exc:  # export_onnx names the argument (out, planning_*)
        fail(str(exc))
    except RuntimeError as exc:  # onnx missing, or the written model disagrees with torch
        exit_with_error("export", str(exc), code=1)
    for note in info.notes:
        print(f"NOTE: {note}")
    m = info.metadata
    what = "Q and scores" if info.planner else "Q"
    checked = f", {what} within {info.max_q_error:.1e} of torch (onnxruntime)" if info.max_q_error is not None else ""
    print(f"wrote {info.path} ({m['crowdrl.encoder']}, {m['crowdrl.exploration']}, humans: {m['crowdrl.humans']}, "
          f"planning: {m['crowdrl.planning'].split(':')[0]}{checked})")
    print(f"run it without torch: python {onnx_example()} {info.path}")
    print(f"evaluate it on the test cases: crowdrl-evaluate checkpoint={info.path}")
    return {"path": str(info.path), "planning_dropped": info.planning_dropped, "planner": info.planner}


if __name__ == "__main__":  # python -m crowdrl.cli.export
    main()
