#!/usr/bin/env python
"""Metric distance for images or a video: ``python predict.py ckpt_path=... input=... camera=...``."""

import sys

import hydra
from omegaconf import DictConfig

from fisheyedepth.cli import model_file_alias, run_command
from fisheyedepth.cli.predict import predict


@hydra.main(config_path="conf", config_name="predict", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_command(predict, cfg)


if __name__ == "__main__":
    sys.argv = model_file_alias(sys.argv)  # model=FILE.onnx (runtime=onnx)
    main()
