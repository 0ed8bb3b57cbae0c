#!/usr/bin/env bash
# Generate the simulated training / validation scenes for `govnesf train`.
#
# Usage: scripts/make_train_data.sh [DATA_DIR] [N_TRAIN] [FRAMES]
#   DATA_DIR  output root (default: data); writes DATA_DIR/train/apartment_sNNNN and
#             DATA_DIR/val/apartment_sNNNN (each a `govnesf sim record` export, see docs/how-to/simulator.md)
#   N_TRAIN   number of training scenes (default 24; seeds SEED_OFFSET .. SEED_OFFSET+N_TRAIN-1)
#   FRAMES    frames per scene (default 80)
# Validation uses seeds 1000-1002 (never training seeds). Existing complete scenes are skipped,
# so the script can be re-run after an interruption. Env: STYLE (default apartment),
# OV_STRIDE (default: SimLSeg's, 4), WIDTH/HEIGHT (default 160x120), PYTHON, SEED_OFFSET (default 0;
# the multi-layout mix uses 2000 so that no training room is a room of the scenario matrix, whose
# seeds are below 100), NO_VAL=1 (skip the validation scenes).
set -euo pipefail
cd "$(dirname "$0")/.."

DATA_DIR="${1:-data}"
N_TRAIN="${2:-24}"
FRAMES="${3:-80}"
STYLE="${STYLE:-apartment}"
WIDTH="${WIDTH:-160}"
HEIGHT="${HEIGHT:-120}"
PYTHON="${PYTHON:-.venv/bin/python}"
SEED_OFFSET="${SEED_OFFSET:-0}"
VAL_SEEDS=(1000 1001 1002)
export HF_HUB_OFFLINE=1

extra=()
if [[ -n "${OV_STRIDE:-}" ]]; then extra+=(--ov-stride "$OV_STRIDE"); fi

record() {  # split seed
  local split="$1" seed="$2"
  local out
  out="$DATA_DIR/$split/$(printf '%s_s%04d' "$STYLE" "$seed")"
  if [[ -f "$out/gt/novel_views.npz" && -f "$out/frames.govrec" ]]; then
    echo "skip $out (exists)"
    return
  fi
  rm -rf "$out"
  mkdir -p "$out"
  echo "record $out"
  "$PYTHON" -m clients.sim.cli record --seed "$seed" --style "$STYLE" --frames "$FRAMES" \
    --width "$WIDTH" --height "$HEIGHT" --depth --previews 1 --points-per-m2 100 \
    "${extra[@]}" --quiet --out "$out"
}

if [[ -z "${NO_VAL:-}" ]]; then
  for seed in "${VAL_SEEDS[@]}"; do record val "$seed"; done
fi
for ((seed = SEED_OFFSET; seed < SEED_OFFSET + N_TRAIN; seed++)); do record train "$seed"; done
du -sh "$DATA_DIR/train" "$DATA_DIR/val"
echo "done"
