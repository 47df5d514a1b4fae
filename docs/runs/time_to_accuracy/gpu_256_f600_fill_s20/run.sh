#!/usr/bin/env bash
# Session 20's one call on a lent GPU machine: cpu_30min's recipe on world 0 for as many epochs as the
# device time allows (fill_budget.py picks them after the first epoch, decay at 80 %), then the
# checkpoint without its optimiser state, in 15 MiB pieces, back to be scored on the CPU machine.
#   bash docs/runs/time_to_accuracy/gpu_256_f600_fill_s20/run.sh BUDGET_SECONDS
# Needs OUT (the folder that comes back) and .whl (hydra-core, omegaconf, antlr4 wheels). train.py is
# stopped a minute after the budget at the latest; its last.ckpt (saved every epoch) still comes back.
set -u -o pipefail
T0=$(date +%s)
BUDGET=${1:-470}                 # seconds from now by which training must end
shift || true
HERE=docs/runs/time_to_accuracy/gpu_256_f600_fill_s20
PY=${PY:-python3}
WORKERS=${WORKERS:-12}
RUN=${RUN:-/tmp/gpu_run}
if [ -d .whl ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD/src:$PWD/$HERE${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
nvidia-smi -L 2>/dev/null
$PY -c "import torch, lightning, hydra; print('torch', torch.__version__, 'lightning', lightning.__version__, 'cuda', torch.cuda.is_available())"
set -x
timeout $((BUDGET + 60)) $PY train.py +experiment=cpu_30min "trainer=${TRAINER:-gpu}" model.compile_kernels=false logger=csv \
  data.generate.workers=$(nproc) data.datamodule.num_workers=$WORKERS hydra.run.dir=$RUN \
  '~callbacks.progress' +trainer.enable_progress_bar=false \
  +callbacks.fill._target_=fill_budget.FillBudget +callbacks.fill.deadline=$((T0 + BUDGET)) \
  +callbacks.fill.record=$OUT/fill.jsonl "$@" 2>&1 | tee $OUT/train.log | grep -v "^\s*$"
rc=$?
set +x
echo "train.py rc=$rc after $(($(date +%s) - T0)) s"
$PY - "$RUN/checkpoints/last.ckpt" /tmp/slim.ckpt <<'PY'
import sys, torch
c = torch.load(sys.argv[1], map_location="cpu", weights_only=True)
c.pop("optimizer_states", None)
torch.save(c, sys.argv[2])
print("slim checkpoint: epoch", c["epoch"], "step", c["global_step"], "lr_step", c["hyper_parameters"]["lr_step"])
PY
split -b 15M -d /tmp/slim.ckpt "$OUT/last.ckpt.part"
sha256sum /tmp/slim.ckpt | tee "$OUT/last.ckpt.sha256"
tar czf "$OUT/record.tar.gz" -C "$RUN" --exclude='*.ckpt' . 2>/dev/null
ls -la "$OUT"
echo "done after $(($(date +%s) - T0)) s"
