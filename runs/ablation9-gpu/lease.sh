#!/usr/bin/env bash
# The GPU lease behind this folder (README.md), from the repository root on the GPU machine:
#   runs/ablation9-gpu/lease.sh MINUTES [RESUME]
# trains `four` and `no_global_skip` from scratch (or from RESUME's float16 weights, as
# tools/train_ablation.py --resume reads them) with seeds 0, 1 and 2: one process a seed,
# side by side on the one GPU (a process's step is bound by its kernel launches, not the
# GPU), each with its own data workers. Then it packs what comes back into $OUT: the six
# float16 weights and one tar of the runs' configs, logs and validation.
# Environment: WORK (/tmp/ablation9), SEEDS (0 1 2), WORKERS (4 a seed), BATCH (32),
# EMA (0: none; else the weights' moving average, this decay a step, is what is exported),
# STEPS (none: each run stops at its step STEPS if the minutes last that long).
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH=. OMP_NUM_THREADS=2 TORCHINDUCTOR_COMPILE_THREADS=1 PYTHONUNBUFFERED=1
W=${WORK:-/tmp/ablation9}
mkdir -p "$W"
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader 2>/dev/null
for s in ${SEEDS:-0 1 2}; do
  python3 tools/train_ablation.py --out "$W/s$s" --minutes "$1" --seeds "$s" \
    --variants four,no_global_skip --batch "${BATCH:-32}" --lr 2e-4 --workers "${WORKERS:-4}" \
    --val-every 250 --ema "${EMA:-0}" --no-progress ${STEPS:+--steps "$STEPS"} ${2:+--resume "$2"} >"$W/s$s.log" 2>&1 &
done
wait
status=0
for s in ${SEEDS:-0 1 2}; do
  echo "== seed $s"; tail -n 8 "$W/s$s.log"
  grep -q '"steps"' "$W/s$s/summary.json" 2>/dev/null || status=1
done
if [ -n "${OUT:-}" ]; then
  cp "$W"/s*/*.safetensors "$OUT"/ 2>/dev/null
  tar -C "$W" -czf "$OUT/runs.tar.gz" --exclude='*.safetensors' --exclude=checkpoint.safetensors .
fi
exit $status
