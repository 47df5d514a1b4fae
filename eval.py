#!/usr/bin/env python
"""Evaluate a checkpoint on a test split: ``python eval.py ckpt_path=PATH [data=kitti360] [...]``."""

import sys

import hydra
from omegaconf import DictConfig

from fisheyedepth.cli import model_file_alias, run_command
from fisheyedepth.cli.evaluate import eval_checkpoint


@hydra.main(config_path="conf", config_name="eval", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_command(eval_checkpoint, cfg)


if __name__ == "__main__":
    sys.argv = model_file_alias(sys.argv)  # model=FILE.onnx (runtime=onnx)
    main()
