"""The installed environment is the one the project promises."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

import fisheyedepth

ROOT = Path(__file__).resolve().parents[1]


def test_version_and_torch_pin():
    assert fisheyedepth.__version__
    assert torch.__version__.split("+")[0] == "2.13.0"


def test_constraints_pin_torch_and_block_torchvision():
    lines = {line.strip() for line in (ROOT / "constraints.txt").read_text().splitlines()}
    assert "torch==2.13.0" in lines
    assert "torchvision==0.0.0" in lines  # no such release: anything that wants torchvision fails to resolve
    assert importlib.util.find_spec("torchvision") is None


def test_lightning_imports():
    import lightning  # noqa: F401  (breaks when a CUDA-only torchvision is installed)


def test_configs_become_objects_only_in_the_commands():
    """``hydra.utils.instantiate`` lives in ``fisheyedepth.cli`` alone; every command is one small module
    there, and the console script points at one of them."""
    package = ROOT / "src" / "fisheyedepth"
    users = sorted(
        str(p.relative_to(package)) for p in package.rglob("*.py") if "instantiate(" in p.read_text()
    )
    assert users and all(u.startswith("cli/") for u in users), users
    commands = sorted(p.stem for p in (package / "cli").glob("*.py"))
    assert commands == ["__init__", "evaluate", "export", "predict", "train"]
    assert max(len(p.read_text().splitlines()) for p in (package / "cli").glob("*.py")) < 150
    scripts = (ROOT / "pyproject.toml").read_text()
    assert 'fisheyedepth-predict = "fisheyedepth.cli.predict:main"' in scripts
    import subprocess
    import sys

    shown = subprocess.run(
        [sys.executable, "-c", "from fisheyedepth.cli.predict import main; main()", "--cfg", "job"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert shown.returncode == 0 and "task_name: predict" in shown.stdout, shown.stderr[-500:]
