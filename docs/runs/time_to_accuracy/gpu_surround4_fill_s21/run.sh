#!/usr/bin/env bash
# Session 21's call on a lent H200: session 20's run.sh (cpu_30min on world 0 for as many epochs as the
# device time allows, chosen after the first epoch by fill_budget.py, decay at 80 %) on the mixed
# surround4 rig, the rig of issue #13's item 3. Scored afterwards on the CPU machine.
#   bash docs/runs/time_to_accuracy/gpu_surround4_fill_s21/run.sh BUDGET_SECONDS
exec bash docs/runs/time_to_accuracy/gpu_256_f600_fill_s20/run.sh "${1:-480}" data.generate.rig=surround4
