#!/usr/bin/env bash
# The GPU runs of docs/how-to/train.md "Training on a GPU" (G1, G2, G3) as one command, on a machine with
# one CUDA GPU and ~16 cores whose python3 has torch but no Open3D, no MiniLM weights and no
# internet (prepare with scripts/gpu/prepare.sh, which writes .gpu/ and .whl/ here):
#
#   bash scripts/gpu/train_gpu.sh OUT_DIR [TOTAL_S] [N_TRAIN]
#
# 1. checks: CUDA is there, tests/mapper/training/test_cuda.py (model and a training step on the GPU match
#    the CPU);
# 2. records the simulated rooms (seeds 0..N_TRAIN-1, default 48, and validation seeds 1000-1002,
#    80 frames at 160 x 120, as scripts/make_train_data.sh) with the simulator's torch ray caster;
# 3. trains the three runs side by side on the one GPU, each with the wall budget left
#    (govnesf train --wall-budget-s), so that everything ends within TOTAL_S seconds (default 540);
# 4. writes OUT_DIR/runs.tgz (each run's export and log.jsonl) and OUT_DIR/driver.log.
# Env: PYTHON (default python3), RUNS (default "gpu_small gpu_small_geo gpu_medium": launch/train_RUN.toml),
# FRAMES (80), JOBS (parallel recordings, default the core count), ALLOW_CPU=1 (a dry run without a GPU).
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:?usage: train_gpu.sh OUT_DIR [TOTAL_S] [N_TRAIN]}
TOTAL=${2:-540}
N_TRAIN=${3:-48}
FRAMES=${FRAMES:-80}
PY=${PYTHON:-python3}
RUNS=${RUNS:-"gpu_small gpu_small_geo gpu_medium"}
JOBS=${JOBS:-$(nproc)}
T0=$(date +%s)
mkdir -p "$OUT"
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/driver.log"; }

if ! "$PY" -c "import zmq, trimesh, threadpoolctl" 2>/dev/null && compgen -G ".whl/*.whl" >/dev/null; then
  # the wheels are for CPython 3.12 on x86-64 (prepare.sh); another Python needs its own
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/govnesf-site \
    .whl/*.whl || { echo "installing .whl/ failed: rerun scripts/gpu/prepare.sh for this Python" >&2; exit 2; }
  export PYTHONPATH=/tmp/govnesf-site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1
# the simulator ray casts with torch (no Open3D there), on the cores: the GPU is for training
export GOVNESF_SIM_RAYCAST=${GOVNESF_SIM_RAYCAST:-torch} GOVNESF_SIM_RAYCAST_DEVICE=${GOVNESF_SIM_RAYCAST_DEVICE:-cpu}
for f in .gpu/sim_text_table.npz .gpu/val_text_embeddings.npz; do
  [[ -f $f ]] || { echo "missing $f: run scripts/gpu/prepare.sh first" >&2; exit 2; }
done

log "1. checks"
"$PY" -c "import torch, numpy; print('torch', torch.__version__, 'numpy', numpy.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')" | tee -a "$OUT/driver.log"
if [[ ${ALLOW_CPU:-0} != 1 ]] && ! "$PY" -c "import sys, torch; sys.exit(not torch.cuda.is_available())"; then
  log "no CUDA device: these runs are sized for a GPU (ALLOW_CPU=1 for a dry run on the CPU)"
  exit 2
fi
"$PY" -m pytest -q -p no:warnings -p no:cacheprovider tests/mapper/training/test_cuda.py 2>&1 | tail -40 | tee -a "$OUT/driver.log" || log "CUDA checks failed (above); training goes on"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader >>"$OUT/driver.log" 2>&1 || true

log "2. record $N_TRAIN training rooms and 3 validation rooms ($FRAMES frames, $JOBS at a time)"
record() {  # split seed
  local out
  out="data_gpu/$1/$(printf 'apartment_s%04d' "$2")"
  [[ -f $out/gt/novel_views.npz && -f $out/frames.govrec ]] && return 0
  rm -rf "$out" && mkdir -p "$out"
  "$PY" scripts/gpu/record.py --table .gpu/sim_text_table.npz -- record --seed "$2" --style apartment \
    --frames "$FRAMES" --width 160 --height 120 --depth --previews 1 --points-per-m2 100 --quiet --out "$out" \
    >"$out.log" 2>&1 || { echo "record $1 $2 failed:"; tail -5 "$out.log"; return 1; }
}
export -f record
export PY FRAMES
mkdir -p data_gpu/train data_gpu/val
{ for s in 1000 1001 1002; do echo "val $s"; done; for ((s = 0; s < N_TRAIN; s++)); do echo "train $s"; done; } |
  xargs -P "$JOBS" -L 1 bash -c 'record "$0" "$1"' || log "some recordings failed (their logs: data_gpu/*/*.log)"
n_rec=$(find data_gpu/train -name novel_views.npz | wc -l)
n_val=$(find data_gpu/val -name novel_views.npz | wc -l)
if ((2 * n_rec < N_TRAIN || n_rec < 1 || n_val < 3)); then
  log "too few rooms recorded ($n_rec of $N_TRAIN training, $n_val of 3 validation)"
  exit 3
fi
cp .gpu/val_text_embeddings.npz data_gpu/val/text_embeddings_minilm-l6-v2.npz
log "recorded: $n_rec training rooms, $(du -sh data_gpu | cut -f1)"

LEFT=$((TOTAL - ($(date +%s) - T0)))
BUDGET=$((LEFT - 110))   # data loading (~40 s), the final validation and export, packing
((BUDGET > 30)) || { log "no time left to train ($LEFT s)"; exit 3; }
log "3. train ($RUNS) side by side, $BUDGET s of steps each"
pids=()
read -ra runs <<<"$RUNS"
for run in "${runs[@]}"; do
  "$PY" -m mapper.training.cli_train --config "launch/train_$run.toml" --wall-budget-s "$BUDGET" --no-progress \
    >"$OUT/$run.log" 2>&1 &
  pids+=($!)
done
status=0
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { status=1; log "run ${runs[$i]} failed (its log: $OUT/${runs[$i]}.log)"; }
done
for run in $RUNS; do tail -2 "$OUT/$run.log" | tee -a "$OUT/driver.log"; done

log "4. pack"
files=()
for run in "${runs[@]}"; do
  d=$(PY_RUN=$run "$PY" -c "import os; from mapper.training.train import load_train_config as l; c = l('launch/train_' + os.environ['PY_RUN'] + '.toml'); print(c.out_dir)") ||
    { log "run $run: no config to find its output"; status=1; continue; }
  for f in "$d/log.jsonl" "$d/export.json" "$d/export.safetensors"; do if [[ -f $f ]]; then files+=("$f"); fi; done
done
if ((${#files[@]})); then
  tar czf "$OUT/runs.tgz" "${files[@]}"
  log "done: $(du -h "$OUT/runs.tgz" | cut -f1) packed, status $status"
else
  log "nothing to pack (every run failed; their logs are in $OUT), status 1"
  status=1
fi
exit $status
