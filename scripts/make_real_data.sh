#!/usr/bin/env bash
# Convert the real RGB-D sequence in ../shared/data/ for the training mix (`extra_train_dirs`).
#
# Usage: scripts/make_real_data.sh DATA_DIR
#   writes DATA_DIR/real/icl_livingroom1/frames.govrec (colour, depth and poses; no ov maps, no
#   labels) from ../shared/data/icl_livingroom1 (ICL-NUIM "living room 1", Open3D layout, 211
#   frames; CC BY 3.0, credit the ICL-NUIM authors). Then train with
#     extra_train_dirs = ["DATA_DIR/real"], extra_train_weight = 0.25   (docs/how-to/train.md)
# `govnesf import` has no resize option, so the recording keeps the camera's 640 x 480 (colour
# stored as lossless PNG); training resizes it to the training scenes' size when it loads it
# (`load_scene(image_wh=...)`: colour by area, depth nearest, intrinsics scaled).
# An existing recording is skipped; the import writes FILE.partial and renames it only when it
# succeeds. The raw data is read in place, never copied. Env: SRC (the sequence), PYTHON.
set -euo pipefail
cd "$(dirname "$0")/.."

if [[ $# -ne 1 ]]; then
  echo "usage: scripts/make_real_data.sh DATA_DIR" >&2
  exit 2
fi
DATA_DIR="$1"
SRC="${SRC:-../shared/data/icl_livingroom1}"
PYTHON="${PYTHON:-.venv/bin/python}"
NAME="$(basename "$SRC")"
OUT="$DATA_DIR/real/$NAME"

if [[ ! -d "$SRC" || ! -f "$SRC/trajectory.log" ]]; then
  echo "make_real_data: $SRC not found (or has no trajectory.log): the ICL-NUIM excerpt is expected" \
    "in ../shared/data/icl_livingroom1 (see ../shared/data/README.md); set SRC=... to use another copy" >&2
  exit 1
fi
out_abs="$(realpath -m "$OUT")"
if [[ "$out_abs/" == "$(pwd -P)/"* ]] && ! git check-ignore -q "$OUT/frames.govrec"; then
  echo "make_real_data: $OUT is inside the repository and not git-ignored; use an ignored DATA_DIR" \
    "(data/, or the shared data root) so the converted sequence is never committed" >&2
  exit 1
fi
mkdir -p "$OUT"
if [[ -f "$OUT/frames.govrec" ]]; then
  echo "skip $OUT/frames.govrec (exists)"
  exit 0
fi
echo "import $SRC -> $OUT/frames.govrec"
start=$SECONDS
"$PYTHON" -m clients.cli import open3d "$SRC" --K 525,525,319.5,239.5 --rgb-encoding png --quiet \
  --out "$OUT/frames.govrec"
echo "done in $((SECONDS - start)) s"
du -sh "$OUT/frames.govrec"
