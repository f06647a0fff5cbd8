#!/usr/bin/env bash
# The GPU lease behind this folder, from the repository root on the GPU machine:
#   runs/dome24-gg-gpu/lease.sh MINUTES [DEVICE [WORKERS [MAX_STEPS]]]
# trains G_s and G_g from the shipped weights with this folder's config.json (the photo
# library built here by `tools/photo_library.py .gpu-lib/photolib256 --size 256` and
# carried), in /tmp/run, then copies to $OUT (default /tmp/out) what comes back: the
# endpoint's float16 export, the snapshots, and the logs. The checkpoint (with Adam's
# state) stays on the machine.
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH=. OMP_NUM_THREADS=4 TORCHINDUCTOR_COMPILE_THREADS=1 PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}; RUN=/tmp/run
MIN=$1; DEV=${2:-cuda}; WORK=${3:-14}; MAX=${4:+--max-steps $4}
mkdir -p "$OUT"; rm -rf "$RUN"
python3 -c 'import torch; print("torch", torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU")'
# shellcheck disable=SC2086
timeout -s TERM 520 python3 -m matscan.cli train --out "$RUN" --config runs/dome24-gg-gpu/config.json --minutes "$MIN" \
  --device "$DEV" --workers "$WORK" $MAX >"$OUT/train.log" 2>&1
echo "train exit $?" >>"$OUT/train.log"
python3 - "$RUN" "$OUT" <<'PY'
import sys, torch
from matscan.train import export_weights
run, out = sys.argv[1:]
export_weights(f"{run}/checkpoint.safetensors", f"{out}/weights.safetensors", dtype=torch.float16)
print("exported")
PY
cp "$RUN"/config.json "$RUN"/log.csv "$RUN"/val.csv "$OUT"/ 2>/dev/null
mkdir -p "$OUT/snapshots"; cp "$RUN"/snapshots/*.safetensors "$OUT/snapshots/" 2>/dev/null
ls -la "$OUT" "$OUT/snapshots"; tail -3 "$RUN/log.csv"
