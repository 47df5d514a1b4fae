#!/usr/bin/env bash
# Session 21: session 19's overfitting probe, which was stopped at step 100, run to its end: the
# network of cpu_30min from scratch on the truth at every pixel of 16 of world 0's training frames
# (splits/probe16.txt), 800 steps (100 passes), decay at 640; then its near-range misses on those frames.
# It ran beside the scoring of the left-lane worlds for its first 500 steps (hence 6.0 s a step there).
# Run from the repository root; row 44's checkpoint (runs_s16/..., not in the repository) only gives the
# network's hyper-parameters.
set -e
cd "$(git rev-parse --show-toplevel)"
mkdir -p runs_s21
export PYTHONPATH=src
PY=.venv/bin/python
NRO=docs/runs/time_to_accuracy/cpu_256_f600_e10_rim1/near_range_outliers.py
PROBE=docs/runs/time_to_accuracy/cpu_256_f600_e10_sweephints1/supervised_probe.py
W0=data/synthetic_kitti360_256_seed0_f600
# the 16 frames: every 30th line of world 0's training split, from the 15th
[ -f $W0/splits/probe16.txt ] || sed -n '15~30p' $W0/splits/train.txt > $W0/splits/probe16.txt
$PY $PROBE runs_s16/cpu30_control/checkpoints/last.ckpt $W0 800 runs_s21/gt_probe800_fit16.ckpt --decay-step 640 --split splits/probe16.txt > runs_s21/gt_probe800_fit16.log 2>&1
$PY $NRO runs_s21/gt_probe800_fit16.ckpt $W0 splits/probe16.txt > runs_s21/nro_fit16_probe16.txt
echo "all done $(date)"
