#!/usr/bin/env bash
# Every measurement docs/how-to/evaluate.md and docs/how-to/train.md quote for one checkpoint, in one go.
#
# Usage: scripts/evaluate_checkpoint.sh CHECKPOINT OUT_DIR [PARTS...]
#   CHECKPOINT  e.g. checkpoints/cpu-small.json
#   OUT_DIR     results: val.txt, results_3d.json / tables_3d.md, results_2d.json / tables_2d.md,
#               density_visibility.txt, rendered_depth_points.txt, real_sequence.{json,md},
#               results_rgb_node.json / tables_rgb_node.md
#   PARTS       any of: val 3d 2d visibility rgbonly real rgbnode (default: all of them)
# Needs the data of scripts/make_train_data.sh (data/val), scripts/make_eval_data.sh (data/eval)
# and, for `real`, ../shared/data/icl_livingroom1. Env: PYTHON (default .venv/bin/python), DATA (data).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ $# -lt 2 ]]; then
    sed -n '2,10p' "$0"
    exit 2
fi
CKPT="$1"
OUT="$2"
shift 2
PARTS=("$@")
ALL_PARTS="val 3d 2d visibility rgbonly real rgbnode"
if [[ ${#PARTS[@]} -eq 0 ]]; then read -r -a PARTS <<< "$ALL_PARTS"; fi
PYTHON="${PYTHON:-.venv/bin/python}"
DATA="${DATA:-data}"
export HF_HUB_OFFLINE=1 OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
if [[ ! -f "$CKPT" ]]; then echo "evaluate_checkpoint: no checkpoint $CKPT" >&2; exit 2; fi
for part in "${PARTS[@]}"; do
    case "$part" in
        val|3d|2d|visibility|rgbonly|real|rgbnode) ;;
        *) echo "evaluate_checkpoint: unknown part $part ($ALL_PARTS)" >&2; exit 2 ;;
    esac
done
mkdir -p "$OUT"
for part in "${PARTS[@]}"; do
    start=$(date +%s)
    echo "[evaluate_checkpoint] $part ..."
    case "$part" in
        val) "$PYTHON" -m mapper.training.cli_train --config launch/train_cpu_small.toml --evaluate "$CKPT" \
                 --val-stride 4 2>&1 | tee "$OUT/val.txt" ;;
        3d) "$PYTHON" -m mapper.training.cli_eval --checkpoint "$CKPT" --data "$DATA/eval" --max-points 20000 \
                --no-2d --averaging-border-px 10 0 --device cpu --quiet \
                --out "$OUT/results_3d.json" --markdown "$OUT/tables_3d.md" ;;
        2d) "$PYTHON" -m mapper.training.cli_eval --checkpoint "$CKPT" --data "$DATA/eval" --novel-views 8 \
                --pixel-stride 2 --no-3d --device cpu --quiet \
                --out "$OUT/results_2d.json" --markdown "$OUT/tables_2d.md" ;;
        visibility) "$PYTHON" benchmarks/studies/density_visibility.py --checkpoint "$CKPT" --data "$DATA/eval" \
                        --max-points 5000 2>&1 | tee "$OUT/density_visibility.txt" ;;
        rgbonly) "$PYTHON" benchmarks/studies/rendered_depth_points.py --frames 240 --threads 1 --checkpoint "$CKPT" \
                     2>&1 | tee "$OUT/rendered_depth_points.txt" ;;
        real) "$PYTHON" benchmarks/studies/real_sequence.py --checkpoint "$CKPT" --max-targets 12 --render-scale 0.5 \
                  --out "$OUT/real_sequence" 2>&1 | tee "$OUT/real_sequence.txt" ;;
        rgbnode) "$PYTHON" -m mapper.training.cli_eval --checkpoint "$CKPT" --data "$DATA/eval" --max-points 20000 \
                     --no-2d --no-oracle --rgb-only-node --device cpu --quiet \
                     --out "$OUT/results_rgb_node.json" --markdown "$OUT/tables_rgb_node.md" ;;
        *) echo "evaluate_checkpoint: unknown part $part ($ALL_PARTS)" >&2; exit 2 ;;
    esac
    echo "[evaluate_checkpoint] $part done in $(( $(date +%s) - start )) s"
done
