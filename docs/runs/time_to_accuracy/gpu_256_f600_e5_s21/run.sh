#!/usr/bin/env bash
# Session 21's second call on the lent H200 (404 s of device time left after the surround4 run):
# cpu_30min on the kitti360 rig's world 0 with session 20's fill_budget.py capped at 10 epochs, to
# repeat cpu_30min (10 epochs, decay after 8) on the GPU. The epochs took 28-34 s on this machine
# (20-26 s in session 20), so the rule chose 5 epochs with the decay after 4: 1,190 steps, half of
# cpu_30min's. It is a shorter schedule, not a control of row 44.
export OUT
RUN=/tmp/gpu_ctrl bash docs/runs/time_to_accuracy/gpu_256_f600_fill_s20/run.sh 320 +callbacks.fill.cap=10
