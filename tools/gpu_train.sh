#!/usr/bin/env bash
# Train the map networks on one GPU from a checkout, with no matscan install and no internet.
#
#   tools/gpu_train.sh --out RUN --minutes M [more `matscan train` flags, e.g. --lr 3e-5]
#
# What it runs (from the repository root, PYTHONPATH=.):
#   python3 -m matscan.cli train --out RUN --minutes M --config CONFIG
# with CONFIG: preset cpu (the shipped network shape, so inference stays fast on a CPU),
# prior v2, device cuda, batch 32 at crop 128, 12 data workers, all four networks, starting
# from matscan/weights/dome24-cpu.safetensors with a fresh Adam at lr 5e-5. Flags after
# --out/--minutes override CONFIG (`matscan train --help`). Rerunning the same command
# resumes RUN from its checkpoint; the run writes one at the end (and every 10 minutes).
#
# Before the run, a smoke test of 3 steps (same shapes, 4 workers, validation included) in
# a temporary folder fails within a minute or two if something is wrong. SMOKE=0 skips it.
#
# Environment (all optional):
#   PYTHON     the interpreter (python3); it needs torch with CUDA, numpy, opencv
#              (cv2), safetensors and tqdm. OpenEXR, tifffile, rawpy are not needed.
#   WHEELS     a folder of wheels for whichever of those are missing (default ./wheels):
#              installed with pip --no-index into ./.gpu-deps, which goes on PYTHONPATH.
#              Make it on a machine with internet, for the GPU machine's Python X.Y:
#                pip download --only-binary=:all: --python-version X.Y \
#                  --platform manylinux2014_x86_64 -d wheels numpy opencv-python-headless safetensors tqdm
#   WORKERS    data worker processes (12: about 27 samples/s each at crop 128, so
#              ~320 samples/s, 10 steps/s of batch 32); BATCH (32); PREFETCH (2 per worker);
#   LR (5e-5); MAPS (diffuse,specular,roughness,normal); PRIOR (v2); DEVICE (cuda);
#   INIT (matscan/weights/dome24-cpu.safetensors; set it empty to train from scratch, as
#   the ablation does: INIT= tools/gpu_train.sh --out runs/ablation-gpu/one_encoder
#   --minutes 9 --variant one_encoder --steps 1500).
set -euo pipefail

cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
WORKERS=${WORKERS:-12}
BATCH=${BATCH:-32}
PREFETCH=${PREFETCH:-2}
LR=${LR:-5e-5}
MAPS=${MAPS:-diffuse,specular,roughness,normal}
PRIOR=${PRIOR:-v2}
DEVICE=${DEVICE:-cuda}
WHEELS=${WHEELS:-wheels}
INIT=${INIT-matscan/weights/dome24-cpu.safetensors}

OUT="" MINUTES=""
ARGS=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --out) OUT=$2; shift 2 ;;
    --minutes) MINUTES=$2; shift 2 ;;
    *) ARGS+=("$1"); shift ;;
  esac
done
if [[ -z "$OUT" || -z "$MINUTES" ]]; then
  echo "usage: tools/gpu_train.sh --out RUN --minutes M [more matscan train flags]" >&2
  exit 2
fi

export PYTHONPATH=".${PYTHONPATH:+:$PYTHONPATH}"
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-4}            # the main process; each data worker uses 1
export TORCHINDUCTOR_COMPILE_THREADS=${TORCHINDUCTOR_COMPILE_THREADS:-1}  # 12 workers compile at once

# --- dependencies ----------------------------------------------------------------------
missing=$("$PYTHON" - <<'EOF'
import importlib.util
need = {"torch": "torch", "numpy": "numpy", "cv2": "opencv-python-headless", "safetensors": "safetensors", "tqdm": "tqdm"}
print(" ".join(pkg for mod, pkg in need.items() if importlib.util.find_spec(mod) is None))
EOF
)
if [[ -n "$missing" ]]; then
  if [[ "$missing" == *torch* ]]; then
    echo "gpu_train: $PYTHON has no torch; set PYTHON to an interpreter with CUDA torch" >&2
    exit 1
  fi
  if [[ ! -d "$WHEELS" ]]; then
    echo "gpu_train: $PYTHON lacks: $missing; put their wheels in ./$WHEELS (see the header of $0)" >&2
    exit 1
  fi
  echo "gpu_train: installing $missing from $WHEELS into .gpu-deps"
  # shellcheck disable=SC2086
  "$PYTHON" -m pip install --quiet --no-index --find-links "$WHEELS" --target .gpu-deps $missing
  export PYTHONPATH="$PYTHONPATH:.gpu-deps"
fi

"$PYTHON" - "$DEVICE" <<'EOF'
import sys, torch
dev = sys.argv[1]
print(f"gpu_train: torch {torch.__version__}, CUDA {torch.version.cuda}, "
      + (f"{torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else "no GPU visible"))
if dev.startswith("cuda") and not torch.cuda.is_available():
    sys.exit("gpu_train: DEVICE is cuda but torch sees no GPU")
EOF

# shared memory carries the batches from the workers: about 5.4 MB a sample at crop 128
SHM_MB=$(df -Pm /dev/shm 2>/dev/null | awk 'NR==2 {print $4}')
NEED_MB=$(( WORKERS * PREFETCH * BATCH * 11 / 2 ))
if [[ -n "$SHM_MB" && "$SHM_MB" -lt "$NEED_MB" ]]; then
  echo "gpu_train: /dev/shm has ${SHM_MB} MB free, the loader may hold ${NEED_MB} MB; prefetch 1" >&2
  PREFETCH=1
fi

config() {  # write the TrainConfig JSON: config FILE WORKERS
  "$PYTHON" - "$1" "$2" "$PRIOR" "$DEVICE" "$BATCH" "$PREFETCH" "$LR" "$INIT" "$MAPS" <<'EOF'
import json, sys
path, workers, prior, device, batch, prefetch, lr, init, maps = sys.argv[1:]
cfg = {"preset": "cpu", "prior": prior, "device": device, "batch": int(batch), "crop": 128,
       "workers": int(workers), "prefetch": int(prefetch), "lr": float(lr), "init": init, "maps": maps.split(",")}
open(path, "w").write(json.dumps(cfg, indent=1) + "\n")
EOF
}

# --- smoke test: a few steps of the same shapes, with validation and a checkpoint ---------
if [[ "${SMOKE:-1}" != 0 ]]; then
  SMOKE_DIR=$(mktemp -d)
  config "$SMOKE_DIR/config.json" 4
  echo "gpu_train: smoke test in $SMOKE_DIR"
  "$PYTHON" -m matscan.cli train --out "$SMOKE_DIR/run" --config "$SMOKE_DIR/config.json" \
    --max-steps 3 --val-every 2 --val-count 4
  "$PYTHON" - "$SMOKE_DIR/run" <<'EOF'
import sys
from matscan.train import load_weights
nets, meta = load_weights(f"{sys.argv[1]}/checkpoint.safetensors")  # on the CPU: saved from CPU copies
assert meta["step"] == "3", meta["step"]
print("gpu_train: smoke test passed (3 steps, validation, checkpoint loads on the CPU)")
EOF
  rm -rf "$SMOKE_DIR"
fi

# --- the run ---------------------------------------------------------------------------------
mkdir -p "$OUT"
config "$OUT/gpu_train.config.json" "$WORKERS"
echo "gpu_train: $PYTHON -m matscan.cli train --out $OUT --minutes $MINUTES --config $OUT/gpu_train.config.json ${ARGS[*]:-}"
"$PYTHON" -m matscan.cli train --out "$OUT" --minutes "$MINUTES" --config "$OUT/gpu_train.config.json" \
  ${ARGS[@]+"${ARGS[@]}"} 2>&1 | tee -a "$OUT/gpu_train.log"
"$PYTHON" - "$OUT" <<'EOF'
import csv, os, sys
log = f"{sys.argv[1]}/log.csv"  # a row every log_every (20) steps
rows = list(csv.DictReader(open(log))) if os.path.isfile(log) else []
if len(rows) >= 2:
    a, b = rows[0], rows[-1]
    rate = (int(b["step"]) - int(a["step"])) / max(1e-9, float(b["seconds"]) - float(a["seconds"]))
    print(f"gpu_train: {rate:.2f} steps/s between logged steps {a['step']} and {b['step']}")
EOF
