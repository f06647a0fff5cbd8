#!/usr/bin/env bash
# The GPU lease behind this folder, from the repository root on the GPU machine:
#   runs/ablation-gpu/lease.sh train MINUTES   (started in the background with setsid)
#   runs/ablation-gpu/lease.sh score           (once WORK.trained exists)
# WORK (default /tmp/ablation-gpu) holds the runs; the machine keeps nothing afterwards.
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH=. OMP_NUM_THREADS=2 TORCHINDUCTOR_COMPILE_THREADS=1 PYTHONUNBUFFERED=1
W=${WORK:-/tmp/ablation-gpu}
case "$1" in
  train)
    python3 tools/train_ablation.py --out "$W" --minutes "$2" --seeds 0,1 --batch 32 --lr 2e-4 \
      --workers 7 --val-every 250 --no-progress >"$W.train.log" 2>&1
    echo "exit $?" >"$W.trained" ;;
  score)  # every weights file on the 8 unlike sets and on 48 materials of the prior they trained on
    for w in "$W"/*.safetensors; do
      n=$(basename "$w" .safetensors)
      (python3 tools/nets_unlike.py "$w" --size 256 --counts 1,2,3,6,10,16,24 >"$W/$n.unlike.txt" 2>&1
       python3 tools/nets_unlike.py "$w" --size 128 --procedural 48 --prior v1 \
         --counts 1,2,3,6,10,16,24 >"$W/$n.procedural.txt" 2>&1) &
    done
    wait
    echo done >"$W.scored" ;;
esac
