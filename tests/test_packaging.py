"""What ``pip install .`` gives a user: a wheel with the Hydra configs inside the package, the
console scripts, the license; an installed ``crowdrl-train`` that composes its configuration outside
the checkout (configs from the package, not from the current directory).

One wheel is built per module (from a copy of the project's files, so that no stale ``build/`` and
no ``*.egg-info`` of the checkout are read or written) and installed with ``pip --target``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = {"crowdrl-train": "crowdrl.cli.train:main", "crowdrl-evaluate": "crowdrl.cli.evaluate:main",
           "crowdrl-reproduce": "crowdrl.cli.reproduce:main", "crowdrl-demo": "crowdrl.cli.demo:main",
           "crowdrl-export": "crowdrl.cli.export:main", "crowdrl-ceiling": "crowdrl.cli.ceiling:main"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("setuptools", minversion="77")  # the build backend (pyproject.toml), in the dev extra
    project = tmp_path_factory.mktemp("project")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, project / name)
    for name in ("src", "conf"):
        shutil.copytree(ROOT / name, project / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    dist = tmp_path_factory.mktemp("dist")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(dist), "."], cwd=project, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (found,) = dist.glob("crowdrl-*.whl")
    return found


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--no-compile", "-q",
                           "--target", str(target), str(wheel)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return target


def test_the_wheel_holds_every_package_every_config_the_license_and_the_console_scripts(wheel):
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/METADATA"))
        entry_points = zf.read(f"{info}/entry_points.txt").decode()
        metadata = zf.read(f"{info}/METADATA").decode()
    configs = sorted(p.relative_to(ROOT / "conf").as_posix() for p in (ROOT / "conf").rglob("*") if p.is_file())
    assert "config.yaml" in configs and "preset/smoke.yaml" in configs and len(configs) > 20
    missing = [c for c in configs if f"crowdrl/conf/{c}" not in names]
    assert not missing, f"configs not in the wheel: {missing}"
    modules = sorted(p.relative_to(ROOT / "src").as_posix() for p in (ROOT / "src" / "crowdrl").rglob("*.py"))
    missing = [m for m in modules if m not in names]
    assert not missing, f"modules not in the wheel (a package missing from pyproject.toml's list?): {missing}"
    assert f"{info}/licenses/LICENSE" in names
    assert "[console_scripts]" in entry_points
    for script, target in SCRIPTS.items():
        assert f"{script} = {target}" in entry_points, entry_points
    requires = [line.split(":", 1)[1].strip() for line in metadata.splitlines() if line.startswith("Requires-Dist:")]
    base = [r for r in requires if "extra ==" not in r]
    assert {r.split(">")[0].split("<")[0].split("=")[0] for r in base} == {
        "torch", "torchrl", "tensordict", "gymnasium", "numpy", "filelock", "hydra-core", "omegaconf"}, base
    assert any(r.startswith("wandb") and "extra == \"train\"" in r for r in requires), requires
    assert any(r.startswith("onnxruntime") and "extra == \"export\"" in r for r in requires), requires
    assert "Project-URL: Paper, https://arxiv.org/abs/2302.06554" in metadata
    assert "License-Expression: MIT" in metadata


def test_an_installed_crowdrl_train_composes_its_config_from_the_package_outside_the_checkout(installed, tmp_path):
    """``crowdrl-train --cfg job`` in an empty folder (no conf/ there, the checkout not on the path
    before the installed copy) prints the composed run configuration and writes nothing."""
    env = {**os.environ, "PYTHONPATH": str(installed), "WANDB_MODE": "offline"}
    where = subprocess.run([sys.executable, "-c", "import crowdrl, crowdrl.resources as r; "
                            "print(crowdrl.__file__); print(r.config_dir())"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr[-2000:]
    module, conf = where.stdout.split()
    assert Path(module).is_relative_to(installed) and Path(conf) == installed / "crowdrl" / "conf", where.stdout
    script = installed / "bin" / "crowdrl-train"
    assert script.is_file()
    proc = subprocess.run([sys.executable, str(script), "--cfg", "job", "preset=smoke", "exploration=re3"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "scenario: circle" in proc.stdout and "name: re3" in proc.stdout and "preset: smoke" in proc.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "composing the config wrote into the current directory"


def test_installed_command_lines_name_themselves_in_their_errors_and_the_onnx_example_ships(installed, tmp_path):
    """A refused ``crowdrl-evaluate`` says ``crowdrl-evaluate: <argument>: ...`` (not a checkout script's
    name) and leaves the current directory empty; ``crowdrl/onnx_example.py`` is installed and runs by its
    path outside the checkout."""
    env = {**os.environ, "PYTHONPATH": str(installed), "WANDB_MODE": "offline"}
    proc = subprocess.run([sys.executable, str(installed / "bin" / "crowdrl-evaluate"), "checkpoint=nope"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.strip() == "crowdrl-evaluate: checkpoint: no checkpoint at nope", proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    pytest.importorskip("onnxruntime")
    example = installed / "crowdrl" / "onnx_example.py"
    proc = subprocess.run([sys.executable, str(example), "missing.onnx"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2 and "model: no file at missing.onnx" in proc.stderr, proc.stderr[-2000:]


def test_in_the_checkout_the_configs_are_the_top_level_conf():
    import crowdrl
    from crowdrl.resources import config_dir

    if not Path(crowdrl.__file__).resolve().is_relative_to(ROOT / "src"):
        pytest.skip(f"crowdrl is imported from {crowdrl.__file__}, not from this checkout")
    assert config_dir() == ROOT / "conf"
    assert not (ROOT / "src" / "crowdrl" / "conf").exists()  # one copy of the configs in git


def test_the_citation_file_cites_this_software_and_the_paper():
    import yaml

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["type"] == "software" and cff["license"] == "MIT"
    (paper,) = cff["references"]
    assert paper["title"] == "Improving robot navigation in crowded environments using intrinsic rewards"
    assert [a["family-names"] for a in paper["authors"]] == ["Martinez-Baselga", "Riazuelo", "Montano"]
    assert paper["year"] == 2023 and "ICRA" in paper["conference"]["name"] and "2302.06554" in paper["url"]
    assert "crowdrl contributors" in (ROOT / "LICENSE").read_text()


def test_a_missing_optional_dependency_names_the_extra_to_install():
    """The base install is the library; what needs the ``train`` extra says so when it is absent."""
    code = """
import sys
import numpy as np
sys.modules["matplotlib"] = None   # as if not installed
sys.modules["rliable"] = None
try:
    import crowdrl.viz
except ImportError as exc:
    print("viz:", exc)
from crowdrl.evaluation.stats import mean_interval
try:
    mean_interval({"a": np.zeros(2)})
except ImportError as exc:
    print("stats:", exc)
import crowdrl.envs, crowdrl.exploration, crowdrl.training   # the library itself imports without them
print("library: ok")
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("viz: crowdrl.viz") and "matplotlib" in lines[0], lines
    assert lines[1].startswith("stats: confidence intervals") and "rliable" in lines[1], lines
    assert all("pip install 'crowdrl[train]'" in line for line in lines[:2]), lines
    assert lines[2] == "library: ok", lines
