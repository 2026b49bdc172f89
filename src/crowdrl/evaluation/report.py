"""What an evaluation reports: the ``eval.json`` record, its CSV row and a Markdown table.

Every ``eval.json`` crowdrl writes (``evaluate.py``, ``train.py``'s test of its best checkpoint, ``reproduce.py``,
``pretrained/``) has one layout, version :data:`EVAL_VERSION`::

    {"format": "crowdrl.eval", "version": 2, "records": [
        {"success_rate": 0.974, "collision_rate": 0.026, ..., "episodes": 1000, "seed": 0, "scenario": "circle",
         "policy": "sgd3qn+egreedy+planning", "checkpoint": "...", "checkpoint_frames": 200704, ...}]}

One record per scenario tested. :func:`read_eval_records` is the one reader: it also reads the layouts written
before version 2 (a flat record, a list of records, a training run's ``{"test_seed", "metrics"}``), and refuses
a newer version or another format, naming the file.

Example::

    from crowdrl.evaluation.report import read_eval_records
    for r in read_eval_records("pretrained/sgd3qn-planning-egreedy-episodes-s0/eval.json"):
        print(r["scenario"], r["success_rate"])
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any, Iterable

from crowdrl import tables
from crowdrl.evaluation.metrics import EpisodeMetrics
from crowdrl.files import atomic_write_bytes, atomic_write_json

EVAL_FORMAT = "crowdrl.eval"
EVAL_VERSION = 2  # 1: the layouts before it (no "format"/"version" keys), read by read_eval_records

# eval.json keys, in table order, and the EpisodeMetrics field each comes from
REPORT_FIELDS = {
    "success_rate": "success_rate",
    "collision_rate": "collision_rate",
    "timeout_rate": "timeout_rate",
    "navigation_time": "navigation_time",
    "average_return": "average_return",
    "discomfort_frequency": "discomfort_frequency",
    "min_separation": "discomfort_min_separation",
}
HEADERS = {"success_rate": "success", "collision_rate": "collision", "timeout_rate": "timeout",
           "navigation_time": "nav time (s)", "average_return": "avg return", "discomfort_frequency": "discomfort",
           "min_separation": "min sep. (m)"}

# The paper's rows (upstream logs, 1000 cases, one seed): return, success, collision, navigation time.
PAPER = {
    "egreedy": {"circle": (0.6312, 0.940, 0.060, 11.318), "square": (0.6396, 0.948, 0.052, 10.545)},
    "noisy": {"circle": (0.5423, 0.937, 0.063, 13.965), "square": (0.5566, 0.921, 0.078, 12.742)},
    "dropout": {"circle": (0.6529, 0.959, 0.041, 11.899), "square": (0.6484, 0.952, 0.048, 11.148)},
    "icm": {"circle": (0.6680, 0.968, 0.032, 11.366), "square": (0.6868, 0.970, 0.030, 10.729)},
    "re3": {"circle": (0.6820, 0.971, 0.029, 11.012), "square": (0.6749, 0.958, 0.042, 10.221)},
    "orca": {"circle": (0.3315, 0.769, 0.222, 13.880), "square": (0.4417, 0.840, 0.151, 12.856)},
    # the other architectures (circle only; the paper gives no collision rate for them)
    "lstm_rl+egreedy": {"circle": (0.5841, 0.903, math.nan, 11.683)},
    "lstm_rl+icm": {"circle": (0.5735, 0.899, math.nan, 10.842)},
    "sarl+egreedy": {"circle": (0.5660, 0.890, math.nan, 11.674)},
    "sarl+icm": {"circle": (0.5737, 0.902, math.nan, 10.834)},
    "mp_rgl+egreedy": {"circle": (0.6273, 0.941, math.nan, 11.958)},
    "mp_rgl+icm": {"circle": (0.6437, 0.956, math.nan, 11.274)},
}


def parse_run_group(text: str) -> tuple[str, list[Path]]:
    """A ``LABEL=RUN[,RUN...]`` group of runs (folders, one per seed), each of which must exist.

    A folder whose name holds commas (a Hydra sweep's ``0-a=1,b=2``) is found by joining the
    comma-separated pieces back together: at each piece, the longest run of pieces that names an
    existing path is taken first.

    >>> parse_run_group("ε-greedy=.,.")
    ('ε-greedy', [PosixPath('.'), PosixPath('.')])

    Raises ``ValueError`` naming the group for a malformed text or a missing folder.
    """
    label, sep, folders = text.partition("=")
    label = label.strip()
    pieces = folders.split(",")
    if not sep or not label or not any(p.strip() for p in pieces):
        raise ValueError(f"expected 'LABEL=RUN[,RUN...]', got {text!r}")
    runs: list[Path] = []
    i = 0
    while i < len(pieces):
        if not pieces[i].strip():  # an empty piece: a stray or trailing comma
            i += 1
            continue
        for j in range(len(pieces), i, -1):  # the longest existing path first
            candidate = ",".join(pieces[i:j]).strip()
            if candidate and Path(candidate).exists():
                runs.append(Path(candidate))
                i = j
                break
        else:
            raise ValueError(f"{label!r}: {pieces[i].strip()} does not exist")
    return label, runs


def paper_value(method: str, scenario: str, key: str) -> float:
    """The paper's value of ``key`` (average_return, success_rate, collision_rate, navigation_time)."""
    row = PAPER.get(method, {}).get(scenario)
    order = ("average_return", "success_rate", "collision_rate", "navigation_time")
    return row[order.index(key)] if row is not None and key in order else math.nan


def eval_record(metrics: EpisodeMetrics, *, scenario: str, seed: int, policy: str, **extra: Any) -> dict[str, Any]:
    """The ``eval.json`` record: the seven metrics plus ``episodes``, ``seed``, ``scenario``, ``policy``."""
    out = {key: getattr(metrics, field) for key, field in REPORT_FIELDS.items()}
    return {**out, "episodes": metrics.episodes, "seed": seed, "scenario": scenario, "policy": policy, **extra}


def _fmt(value: Any) -> str:
    if value is None:  # an undefined metric as read back from strict JSON (null)
        return "–"
    if isinstance(value, float):
        return "–" if math.isnan(value) else f"{value:.4f}" if abs(value) < 1 else f"{value:.3f}"
    return str(value)


def markdown_table(records: Iterable[dict[str, Any]], label_keys: tuple[str, ...] = ("policy", "scenario")) -> str:
    """One row per record: its labels, then the seven metrics."""
    head = [*label_keys, *(HEADERS[k] for k in REPORT_FIELDS)]
    return tables.markdown_table(head, ([*(str(r.get(k, "")) for k in label_keys), *(_fmt(r[k]) for k in REPORT_FIELDS)]
                                        for r in records))


def eval_file(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``eval.json`` payload (version :data:`EVAL_VERSION`) holding ``records``."""
    return {"format": EVAL_FORMAT, "version": EVAL_VERSION, "records": list(records)}


def write_records(folder: Path | str, records: list[dict[str, Any]], stem: str = "eval") -> tuple[Path, Path]:
    """``<stem>.json`` (:func:`eval_file`) and ``<stem>.csv`` (one row per record) in ``folder``, written atomically."""
    folder = Path(folder)
    if not records:
        raise ValueError(f"{folder / stem}.json: no records to write")
    json_path, csv_path = folder / f"{stem}.json", folder / f"{stem}.csv"
    atomic_write_json(json_path, eval_file(records))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(records[0]))
    writer.writeheader()
    writer.writerows(records)
    atomic_write_bytes(csv_path, buf.getvalue().encode())
    return json_path, csv_path


class RecordError(ValueError):
    """A record read back (``eval.json``, ``summary.json``) is not what crowdrl writes; the message
    names the file and the field."""


RATE_FIELDS = ("success_rate", "collision_rate", "timeout_rate", "discomfort_frequency")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_metrics(metrics: Any, where: str, *, separation_key: str = "min_separation") -> dict[str, Any]:
    """``metrics`` (an ``eval.json`` record, or ``summary.json``'s ``test.metrics`` with
    ``separation_key="discomfort_min_separation"``) checked field by field; :class:`RecordError`
    naming ``where`` and the field otherwise: rates in [0, 1], ``episodes`` an integer >= 1, the
    navigation time finite and >= 0 or null, the min separation and the average return finite or null
    (a collision step's overlap makes the separation negative)."""
    if not isinstance(metrics, dict):
        raise RecordError(f"{where}: expected a JSON object of metrics, got {type(metrics).__name__}")

    def need(key: str, ok: bool, what: str) -> None:
        if not ok:
            got = metrics.get(key, "(missing)")
            raise RecordError(f"{where}: {key}: must be {what}, got {got!r}")

    episodes = metrics.get("episodes")
    need("episodes", isinstance(episodes, int) and not isinstance(episodes, bool) and episodes >= 1, "an integer >= 1")
    for key in RATE_FIELDS:
        need(key, _number(metrics.get(key)) and 0 <= metrics[key] <= 1, "a number in [0, 1]")
    value = metrics.get("navigation_time", "(missing)")
    need("navigation_time", value is None or (_number(value) and value >= 0), "a finite number >= 0 or null")
    # the mean surface distance over discomfort steps, the collision step included: an overlap there is negative
    value = metrics.get(separation_key, "(missing)")
    need(separation_key, value is None or _number(value), "a finite number (negative: an overlap) or null")
    value = metrics.get("average_return", "(missing)")
    need("average_return", value is None or _number(value), "a finite number or null")
    return metrics


def _read_json(path: Path) -> Any:
    """Any JSON value read from ``path``; :class:`RecordError` naming the file when missing or not JSON."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise RecordError(f"{path}: missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RecordError(f"{path}: not valid JSON ({exc})") from None


def read_json_record(path: Path | str) -> dict[str, Any]:
    """A JSON object read from ``path``; :class:`RecordError` naming the file for anything else."""
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, dict):
        raise RecordError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def _legacy_run_test(data: dict[str, Any], path: Path) -> dict[str, Any]:
    """A training run's ``eval.json`` before version 2 (``{"checkpoint_frames", "test_seed", "metrics"}``, the
    metrics named as in ``summary.json``) as a record; the scenario from the run's ``config.yaml``."""
    metrics = check_metrics(data.get("metrics"), f"{path}: metrics", separation_key="discomfort_min_separation")
    record: dict[str, Any] = {key: metrics.get(field) for key, field in REPORT_FIELDS.items()}
    record.update(episodes=metrics["episodes"], seed=data.get("test_seed"), scenario=_run_scenario(path.parent, {}),
                  checkpoint_frames=data.get("checkpoint_frames"))
    return record


def read_eval_records(path: Path | str) -> list[dict[str, Any]]:
    """Every record of an ``eval.json`` (any version up to :data:`EVAL_VERSION`), each checked
    (:func:`check_metrics`); :class:`RecordError` naming the file and what differs otherwise (another format,
    a newer version, a bad field)."""
    path = Path(path)
    data = _read_json(path)
    if isinstance(data, list):  # version 1: several scenarios (pretrained/)
        records = data
    elif isinstance(data, dict) and ("format" in data or "version" in data):
        if data.get("format") != EVAL_FORMAT:
            raise RecordError(f"{path}: format: expected {EVAL_FORMAT!r}, got {data.get('format')!r}")
        version = data.get("version")
        if not (isinstance(version, int) and not isinstance(version, bool) and 2 <= version):
            raise RecordError(f"{path}: version: expected an integer >= 2, got {version!r}")
        if version > EVAL_VERSION:
            raise RecordError(f"{path}: version {version} was written by a newer crowdrl; this one reads versions up "
                              f"to {EVAL_VERSION} (upgrade crowdrl to read it)")
        records = data.get("records")
        if not isinstance(records, list) or not records:
            raise RecordError(f"{path}: records: expected a non-empty list, got {records!r}")
    elif isinstance(data, dict) and "metrics" in data:  # version 1: a training run's own test
        return [_legacy_run_test(data, path)]
    elif isinstance(data, dict):  # version 1: one flat record (evaluate.py, reproduce.py)
        records = [data]
    else:
        raise RecordError(f"{path}: expected a JSON object, got {type(data).__name__}")
    for i, record in enumerate(records):
        check_metrics(record, f"{path}: records[{i}]" if len(records) > 1 else str(path))
    return records


def read_eval_record(path: Path | str) -> dict[str, Any]:
    """The one record of an ``eval.json`` (:func:`read_eval_records`); :class:`RecordError` when it holds several."""
    records = read_eval_records(path)
    if len(records) != 1:
        scenarios = ", ".join(str(r.get("scenario")) for r in records)
        raise RecordError(f"{path}: holds {len(records)} records ({scenarios}); expected one")
    return records[0]


def read_scenario_record(path: Path | str, scenario: str) -> dict[str, Any]:
    """The record of ``scenario`` in an ``eval.json`` (:func:`read_eval_records`); :class:`RecordError` naming the
    scenarios it holds otherwise."""
    records = read_eval_records(path)
    found = [r for r in records if r.get("scenario") == scenario]
    if len(found) != 1:
        held = ", ".join(str(r.get("scenario")) for r in records)
        raise RecordError(f"{path}: {len(found)} records on {scenario} (it holds: {held}); expected one")
    return found[0]


def read_summary(path: Path | str) -> dict[str, Any]:
    """A run's ``summary.json`` read back: its ``test.metrics`` checked (:func:`check_metrics`) and ``wall_s``,
    ``test_s``, ``run_s`` finite numbers >= 0 when present; :class:`RecordError` naming the file and field."""
    data = read_json_record(path)
    test = data.get("test")
    if not isinstance(test, dict):
        raise RecordError(f"{path}: test: expected a JSON object, got {test!r}")
    check_metrics(test.get("metrics"), f"{path}: test.metrics", separation_key="discomfort_min_separation")
    for key in ("wall_s", "test_s", "run_s"):
        if key in data and not (_number(data[key]) and data[key] >= 0):
            raise RecordError(f"{path}: {key}: must be a finite number >= 0, got {data[key]!r}")
    return data


HUMAN_KEYS_SHOWN = ("human_model", "robot_visible", "social_force_share", "linear_share")  # a crowd changed at test


def _run_scenario(run_dir: Path, record: dict[str, Any]) -> Any:
    """The scenario the run in ``run_dir`` trained (and tested) on: its ``config.yaml``'s, else the record's."""
    config = run_dir / "config.yaml"
    if config.is_file():
        from omegaconf import OmegaConf

        try:
            return OmegaConf.select(OmegaConf.load(config), "env.scenario", default=None)
        except Exception:  # a config.yaml that does not parse: the record's own word
            pass
    return record.get("train_scenario")


def check_against_summary(record: dict[str, Any], path: Path | str, run_dir: Path | str) -> dict[str, Any]:
    """``record`` (read from ``path``, a test of the run in ``run_dir``) cross-checked against the run's own
    ``summary.json`` where both describe the same test: the run's best checkpoint (the same
    ``checkpoint_frames``), its training scenario, the same test seed and number of cases, and the crowd
    it trained with. Each metric must then agree (to 1e-9); :class:`RecordError` naming both files and the
    field otherwise (a hand-edited record). A run without ``summary.json``, or a record of another test, is
    returned as it is."""
    run_dir = Path(run_dir)
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        return record
    test = read_summary(summary_path)["test"]
    metrics = test["metrics"]
    checkpoint = record.get("checkpoint")
    same = (record.get("checkpoint_frames") == test.get("checkpoint_frames")
            and (checkpoint is None or Path(str(checkpoint)).name == "best.pt")
            and record.get("seed") == test.get("test_seed") and record.get("episodes") == metrics["episodes"]
            and record.get("scenario") == _run_scenario(run_dir, record)
            and not any(key in record for key in HUMAN_KEYS_SHOWN))
    if not same:
        return record
    for key, field in REPORT_FIELDS.items():  # the summary.json field of each eval.json metric
        mine, theirs = record.get(key), metrics.get(field)
        if (mine is None) != (theirs is None) or (mine is not None and not math.isclose(mine, theirs, rel_tol=1e-9,
                                                                                           abs_tol=1e-9)):
            raise RecordError(f"{path}: {key}: {mine!r} disagrees with the run's own {summary_path} (test.metrics."
                              f"{field}: {theirs!r}) on the same checkpoint, scenario and test cases; the record was "
                              f"edited or belongs to another run: remove it and rerun to test the run again")
    return record


def read_run_eval_record(path: Path | str, run_dir: Path | str) -> dict[str, Any]:
    """An ``eval.json`` record of the run in ``run_dir`` read back (:func:`read_eval_record`) and cross-checked
    against the run's ``summary.json`` (:func:`check_against_summary`)."""
    return check_against_summary(read_eval_record(path), path, run_dir)


def read_own_test_record(run_dir: Path | str) -> dict[str, Any]:
    """The test a training run made of itself (``train.py``'s top-level ``eval.json``: its best
    checkpoint on its training scenario; ``summary.json``'s ``test`` when ``eval.json`` is missing), as an
    ``eval.json`` record (:data:`REPORT_FIELDS`, ``episodes``, ``seed``, ``scenario`` from its ``config.yaml``,
    ``checkpoint_frames``, ``source``); :class:`RecordError` naming the file and field otherwise."""
    run_dir = Path(run_dir)
    path = run_dir / "eval.json"
    if path.is_file():
        record = dict(read_eval_record(path))
    elif (run_dir / "summary.json").is_file():
        path = run_dir / "summary.json"
        record = _legacy_run_test(read_summary(path)["test"], path)
    else:
        raise RecordError(f"{run_dir}: no eval.json or summary.json (not a finished training run)")
    record["source"] = str(path)
    return record


def run_test_scenarios(run_dir: Path | str) -> list[str]:
    """The scenarios the run in ``run_dir`` holds a test record on: each ``eval-<scenario>/eval.json``,
    and its training scenario when ``train.py`` tested it (a top-level ``eval.json`` or ``summary.json``)."""
    run_dir = Path(run_dir)
    found = {p.parent.name[len("eval-"):] for p in run_dir.glob("eval-*/eval.json")}
    if (run_dir / "eval.json").is_file() or (run_dir / "summary.json").is_file():
        scenario = _run_scenario(run_dir, {})
        if isinstance(scenario, str):
            found.add(scenario)
    return sorted(found)


def read_run_test_record(run_dir: Path | str, scenario: str) -> dict[str, Any]:
    """The run's test record on ``scenario``: ``eval-<scenario>/eval.json`` when present
    (:func:`read_run_eval_record`), else the run's own test when it trained on ``scenario``
    (:func:`read_own_test_record`); :class:`RecordError` saying which record is missing otherwise."""
    run_dir = Path(run_dir)
    path = run_dir / f"eval-{scenario}" / "eval.json"
    if path.is_file():
        return read_run_eval_record(path, run_dir)
    if (run_dir / "eval.json").is_file() or (run_dir / "summary.json").is_file():
        trained = _run_scenario(run_dir, {})
        if trained == scenario:
            return read_own_test_record(run_dir)
        where = f"its own test (eval.json) is on {trained}" if trained else "it has no config.yaml naming its scenario"
    else:
        where = "and no test of its own (eval.json)"
    raise RecordError(f"{run_dir}: no eval-{scenario}/eval.json, {where}; test it there with evaluate.py "
                      f"checkpoint=<run> env={scenario} hydra.run.dir=<run>/eval-{scenario}")
