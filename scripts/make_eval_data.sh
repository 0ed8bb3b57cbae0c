#!/usr/bin/env bash
# Generate the held-out evaluation scenes for `govnesf evaluate` (docs/how-to/evaluate.md).
#
# Usage: scripts/make_eval_data.sh [DATA_DIR] [N_SCENES] [FRAMES]
#   DATA_DIR  output root (default: data/eval); writes DATA_DIR/<style>_sNNNN for both styles:
#             apartment (the training style) and studio (a style the model never saw)
#   N_SCENES  scenes per style (default 3; seeds 2000 .. 2000+N_SCENES-1)
#   FRAMES    frames per scene (default 80)
# Seeds 2000+ are used by neither training (0 .. N_TRAIN-1) nor validation (1000-1002), see
# scripts/make_train_data.sh. Each scene is a `govnesf sim record` export with depth and
# SimLSeg features (docs/how-to/simulator.md), plus gt/novel_ov.npy: SimLSeg run on the ground-truth image
# of each novel view (scripts/novel_view_ov.py), the "2D model at the novel view" reference.
# Complete scenes are skipped, so the script can be re-run after an interruption.
# Env: STYLES (default "apartment studio"), SEED0 (default 2000), WIDTH/HEIGHT (160x120),
# NOVEL_VIEWS (default 8), POINTS_PER_M2 (default 200), PYTHON.
set -euo pipefail
cd "$(dirname "$0")/.."

DATA_DIR="${1:-data/eval}"
N_SCENES="${2:-3}"
FRAMES="${3:-80}"
STYLES="${STYLES:-apartment studio}"
SEED0="${SEED0:-2000}"
WIDTH="${WIDTH:-160}"
HEIGHT="${HEIGHT:-120}"
NOVEL_VIEWS="${NOVEL_VIEWS:-8}"
POINTS_PER_M2="${POINTS_PER_M2:-200}"
PYTHON="${PYTHON:-.venv/bin/python}"
export HF_HUB_OFFLINE=1

for style in $STYLES; do
  for ((i = 0; i < N_SCENES; i++)); do
    seed=$((SEED0 + i))
    out="$DATA_DIR/$(printf '%s_s%04d' "$style" "$seed")"
    if [[ -f "$out/gt/novel_ov.npy" && -f "$out/frames.govrec" ]]; then
      echo "skip $out (exists)"
      continue
    fi
    rm -rf "$out"
    mkdir -p "$out"
    echo "record $out"
    "$PYTHON" -m clients.sim.cli record --seed "$seed" --style "$style" --frames "$FRAMES" \
      --width "$WIDTH" --height "$HEIGHT" --depth --previews 1 --points-per-m2 "$POINTS_PER_M2" \
      --novel-views "$NOVEL_VIEWS" --quiet --out "$out"
    "$PYTHON" scripts/novel_view_ov.py "$out"
  done
done
du -sh "$DATA_DIR"
echo "done"
