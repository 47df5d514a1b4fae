#!/usr/bin/env bash
# Train several recipes side by side on one GPU machine and score each on held-out synthetic worlds
# (BENCHMARKS.md, "Time to accuracy": the GPU rows). Every variant trains on world 0 and is scored,
# at its last checkpoint, on the worlds named by SEEDS. A variant is one line of VARIANTS:
#   NAME OVERRIDE [OVERRIDE ...]          (Hydra overrides of train.py)
# Usage: SEEDS="1001 1002 1003" OUT=out [TRAIN_LIMIT=seconds] bash scripts/research/device_sweep.sh VARIANTS
# A GPU machine without the project's environment needs the hydra-core, omegaconf and antlr4 wheels.
# Measured on an H100 (16 cores): three make-train recipes side by side ran 5 it/s each, about 7 min
# for 22 of their 24 epochs (the 200-frame recipe of the time), plus 2-3 min of rendering: give one
# run two recipes at most. Four cpu_30min variants beside a surround4 one (a second
# sweep) ran 3.6-3.7 it/s each at 256 px, 10 epochs in about 11 minutes; rendering every world first
# (3 workers each, both sweeps at once) had taken 12 minutes, so the training world now renders first
# on every core and the held-out worlds render while the variants train.
# Run it under setsid: it outlives the shell that started it, and OUT is collected afterwards.
# Writes OUT/sweep.tar.gz (each run's results, held-out results, metrics.csv and config; no checkpoints)
# and OUT/summary.md (one row per run, scripts/research/heldout.py's format).
set -u -o pipefail
VARIANTS=$1
SEEDS=${SEEDS:-1001 1002 1003}
RIG=${RIG:-kitti360}
FRAMES=${FRAMES:-200}            # the held-out worlds' renders (scripts/research/heldout.py)
TRAIN_FRAMES=${TRAIN_FRAMES:-600}  # world 0 as train.py's default renders it (conf/data/synthetic.yaml)
WORKERS=${WORKERS:-2}
PY=${PY:-python3}
RUNS=${RUNS:-sweep_runs}
mkdir -p "$RUNS" "$OUT"

render() {  # seed frames workers
  local dir=data/synthetic_${RIG}_256_seed$1_f$2
  [ -d "$dir" ] || $PY -m fisheyedepth.cli.synthetic --out "$dir" --rig "$RIG" --frames "$2" \
    --size 256 --seed "$1" --supersample 2 --workers "$3" --quiet
}
# the training world first, on every core; the held-out worlds while the variants train (scoring
# waits for them: $RUNS/.rendered)
render 0 "$TRAIN_FRAMES" "$(nproc)"
rm -f "$RUNS/.rendered"
(for s in $SEEDS; do render "$s" "$FRAMES" "${RENDER_WORKERS:-3}" & done; wait; touch "$RUNS/.rendered") &

# progress while training: the last logged row of every run, every 30 s (survives a timeout)
(while sleep 30; do
  for m in "$RUNS"/*/logs/version_0/metrics.csv; do [ -f "$m" ] && echo "$m $(tail -n 1 "$m" | cut -c1-80)"; done \
    >"$OUT/progress.txt" 2>/dev/null
  cp "$RUNS"/*.log "$OUT/" 2>/dev/null
done) &
watcher=$!

while read -r name overrides; do
  [ -z "$name" ] || [ "${name:0:1}" = "#" ] && continue
  (
    start=$(date +%s)
    # shellcheck disable=SC2086
    timeout "${TRAIN_LIMIT:-0}" $PY train.py trainer=gpu data.datamodule.num_workers=$WORKERS data.generate.rig=$RIG \
      hydra.run.dir="$RUNS/$name" logger=csv $overrides >"$RUNS/$name.log" 2>&1
    echo "$name trained rc=$? in $(($(date +%s) - start)) s" | tee -a "$RUNS/$name.log"
    while [ ! -f "$RUNS/.rendered" ]; do sleep 5; done
    $PY scripts/research/heldout.py "$RUNS/$name" --rig "$RIG" --seeds $SEEDS --set device=cuda \
      >"$RUNS/$name.row" 2>>"$RUNS/$name.log"
    echo "$name scored in $(($(date +%s) - start)) s" | tee -a "$RUNS/$name.log"
  ) &
done <"$VARIANTS"
wait $(jobs -p | grep -v "^$watcher$")
kill "$watcher"

{
  echo "seeds: $SEEDS, rig $RIG"
  for row in "$RUNS"/*.row; do tail -n 1 "$row"; done
} | tee "$OUT/summary.md"
tar czf "$OUT/sweep.tar.gz" --exclude='*.ckpt' --exclude='*.png' "$RUNS"
