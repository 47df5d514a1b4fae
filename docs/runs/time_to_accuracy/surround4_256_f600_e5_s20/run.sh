#!/usr/bin/env bash
# session 20: the mixed rig at today's cpu_30min (5 epochs, decay after 4), then its dev and held-out worlds
set -x
export PYTHONPATH=src
.venv/bin/python train.py +experiment=cpu_30min data.generate.rig=surround4 trainer.max_epochs=5 model.lr_step=4 \
  hydra.run.dir=runs_s20/surround4_e5 '~callbacks.progress' +trainer.enable_progress_bar=false > runs_s20/surround4_e5.log 2>&1
echo "train rc=$? $(date)"
.venv/bin/python scripts/heldout.py runs_s20/surround4_e5 --rig surround4 --seeds 1001 1002 > runs_s20/s4_dev.md 2>>runs_s20/s4_score.log
echo "dev $(date)"
.venv/bin/python scripts/heldout.py runs_s20/surround4_e5 --rig surround4 --seeds 2001 2002 > runs_s20/s4_ho.md 2>>runs_s20/s4_score.log
echo "held out $(date)"
