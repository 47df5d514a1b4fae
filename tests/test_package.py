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
