"""Checkpoints load with ``weights_only=True``: a pickled payload is refused and never runs, the
files this project writes (and wrote) load, a payload that could not be loaded safely is not written."""

from __future__ import annotations

import math
import os
import shlex
from collections import OrderedDict, namedtuple

import numpy as np
import pytest
import torch

from crowdrl.training.checkpoint import (FORMAT_VERSION, CheckpointError, config_fingerprint, load_checkpoint,
                                         save_checkpoint)
from crowdrl.training.config import RunConfig, to_dict


class _Payload:
    """Unpickling this runs a shell command that creates ``marker``."""

    def __init__(self, marker) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {shlex.quote(str(self.marker))}",)


def test_a_pickled_payload_is_refused_naming_the_file_and_runs_nothing(tmp_path):
    control, marker = tmp_path / "control", tmp_path / "marker"
    torch.save({"format": FORMAT_VERSION, "net": _Payload(control)}, tmp_path / "control.pt")
    torch.load(tmp_path / "control.pt", weights_only=False)  # the unsafe load that used to be done
    assert control.exists(), "the payload must be live for the test to mean anything"

    path = tmp_path / "evil.pt"
    torch.save({"format": FORMAT_VERSION, "fingerprint": "x", "net": {"w": torch.ones(2), "b": _Payload(marker)}}, path)
    with pytest.raises(CheckpointError, match=r"evil\.pt was refused: it holds a pickled Python object \(posix\.system"):
        load_checkpoint(path)
    from crowdrl.training.pipeline import load_trained_network

    with pytest.raises(CheckpointError, match=r"evil\.pt was refused"):
        load_trained_network(path)
    assert not marker.exists(), "the refused checkpoint ran its payload"


def test_garbage_is_reported_as_corrupt_without_advising_an_unsafe_load(tmp_path):
    path = tmp_path / "noise.pt"
    path.write_bytes(b"PK\x03\x04" + np.random.default_rng(0).bytes(3000))  # a torch file's header, then noise
    with pytest.raises(CheckpointError, match=r"noise\.pt is not a readable checkpoint \(truncated or corrupt\?\)") as err:
        load_checkpoint(path)
    assert "weights_only" not in str(err.value)


def _old_layout() -> dict:
    """A ``last.pt`` and a ``best.pt`` as the trainer has written them since format 1 (with ``torch.save``)."""
    net = OrderedDict(w=torch.randn(3, 2), b=torch.zeros(3))
    param = torch.nn.Parameter(torch.zeros(3))
    adam = torch.optim.Adam([param])
    param.grad = torch.ones(3)
    adam.step()  # its state: int step keys, tensors
    counters = {"frames": 192, "updates": 40, "episodes": 3, "update_credit": 0.25, "next_train_episode": 19,
                "best_val": -math.inf, "best_frames": -1, "last_val": 96, "last_checkpoint": 192,
                "history": [(96, 0.25), (192, 0.5)]}
    last = {"format": 1, "fingerprint": "abc", "loss": net, "optimizer": adam.state_dict(), "counters": counters,
            "torch_rng": torch.get_rng_state(), "cuda_rng": None, "config": to_dict(RunConfig()), "wandb_id": None,
            "env": {"format": 1, "split": "train", "seed": 0, "num_envs": 4, "num_humans": 4, "min_humans": None,
                    "next_episode": 19, "tensors": {"state.robot_position": torch.zeros(4, 2)}},
            "pending_episodes": [(1, 0.5, 30), (2, -0.25, 12, 1.5)], "intrinsic_stats": None, "intrinsic_norm": None}
    best = {"format": 1, "fingerprint": "abc", "net": net, "config": to_dict(RunConfig()), "frames": 96,
            "val": {"success_rate": 0.25, "navigation_time": math.nan, "episodes": 4}}
    return {"last.pt": last, "best.pt": best}


@pytest.mark.parametrize("name", ["last.pt", "best.pt"])
def test_checkpoints_in_the_layout_written_so_far_still_load(tmp_path, name):
    saved = _old_layout()[name]
    torch.save(saved, tmp_path / name)  # as the trainer saved before loads became weights_only
    data = load_checkpoint(tmp_path / name, "abc")
    assert data.keys() == saved.keys() and data["config"] == saved["config"]
    assert torch.equal(data["net" if name == "best.pt" else "loss"]["w"], saved["net" if name == "best.pt" else "loss"]["w"])
    if name == "last.pt":
        assert data["counters"] == saved["counters"] and torch.equal(data["torch_rng"], saved["torch_rng"])
        assert data["pending_episodes"] == saved["pending_episodes"]


def test_a_file_of_another_format_gets_a_clear_error(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"net": {"w": torch.ones(1)}}, path)  # no format number
    with pytest.raises(CheckpointError, match=rf"old\.pt is not a crowdrl checkpoint of format {FORMAT_VERSION}"):
        load_checkpoint(path)
    torch.save({"format": FORMAT_VERSION + 1, "net": {"w": torch.ones(1)}}, path)
    with pytest.raises(CheckpointError, match=rf"old\.pt .*found format {FORMAT_VERSION + 1}, expected {FORMAT_VERSION}"):
        load_checkpoint(path)


def test_save_and_load_round_trip(tmp_path):
    payload = _old_layout()["last.pt"]
    del payload["format"], payload["fingerprint"]
    save_checkpoint(tmp_path / "c.pt", payload, "fp")
    data = load_checkpoint(tmp_path / "c.pt", "fp")
    assert data["format"] == FORMAT_VERSION and data["fingerprint"] == "fp"
    assert data["counters"] == payload["counters"] and data["config"] == payload["config"]
    assert all(torch.equal(data["loss"][k], v) for k, v in payload["loss"].items())


@pytest.mark.parametrize("value, where", [
    (np.float64(0.5), r"\['val'\]\['score'\]"),
    (np.zeros(2), r"\['val'\]\['score'\]"),
    (namedtuple("Pair", "a b")(1, 2), r"\['val'\]\['score'\]"),
])
def test_a_payload_that_could_not_be_loaded_safely_is_not_written(tmp_path, value, where):
    with pytest.raises(TypeError, match=rf"checkpoint payload{where} is a .*plain containers"):
        save_checkpoint(tmp_path / "c.pt", {"val": {"score": value}}, "fp")
    assert not (tmp_path / "c.pt").exists()


def test_an_omegaconf_config_is_not_written(tmp_path):
    from omegaconf import OmegaConf

    with pytest.raises(TypeError, match=r"checkpoint payload\['config'\] is a omegaconf"):
        save_checkpoint(tmp_path / "c.pt", {"config": OmegaConf.structured(RunConfig())}, "fp")


def test_a_saved_replay_buffer_holds_no_uninitialised_bytes():
    """train.save_buffer=true: the slots never written (torch.empty's leftovers) are zero in the
    checkpoint, so identical runs write identical last.pt files."""
    import io

    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from crowdrl.training.factories import buffer_state_dict

    saved = []
    for garbage in (7.0, -3.0):  # what uninitialised memory happened to hold in two identical runs
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=2)
        buffer.extend(TensorDict({"a": torch.ones(3, 2), "c": torch.ones(3, dtype=torch.int64)}, [3]))
        stored = buffer.state_dict()["_storage"]["_storage"]
        stored["a"][3:], stored["c"][3:] = garbage, int(garbage)
        buf = io.BytesIO()
        torch.save(buffer_state_dict(buffer), buf)
        saved.append(buf.getvalue())
        state = buffer_state_dict(buffer)["_storage"]["_storage"]
        assert state["a"][3:].eq(0).all() and state["c"][3:].eq(0).all() and state["a"][:3].eq(1).all()
    assert saved[0] == saved[1]


def test_a_text_file_given_as_a_checkpoint_is_named_not_a_torch_file(tmp_path):
    """Not a bare "105" (the unpickler's KeyError) at the end of the message."""
    path = tmp_path / "notes.pt"
    path.write_text("hello\nworld\n")
    with pytest.raises(CheckpointError, match=r"notes\.pt is not a crowdrl checkpoint \(not a torch file"):
        load_checkpoint(path)


def test_a_fingerprint_mismatch_names_each_key_that_differs_and_both_values(tmp_path):
    """config.yaml edited after the run: the refusal names env.num_humans and seed, with both values."""
    stored = to_dict(RunConfig())
    path = tmp_path / "last.pt"
    save_checkpoint(path, {"config": stored}, config_fingerprint(stored))
    edited = to_dict(RunConfig(seed=3))
    edited["env"]["num_humans"] = 7
    edited["train"]["total_frames"] = 5  # a budget: not part of the fingerprint, not named
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, config_fingerprint(edited), config=edited)
    message = str(err.value)
    assert "env.num_humans: 7 here, 10 in the checkpoint" in message and "seed: 3 here, 0 in the checkpoint" in message
    assert "total_frames" not in message
