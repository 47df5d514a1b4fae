#!/usr/bin/env python
"""Export a trained network: ``python export.py ckpt_path=... format=onnx|torchscript [size=[W,H]]``."""

import hydra
from omegaconf import DictConfig

from fisheyedepth.cli import run_command
from fisheyedepth.cli.export import export


@hydra.main(config_path="conf", config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_command(export, cfg)


if __name__ == "__main__":
    main()
