#!/usr/bin/env bash
# Prepare what scripts/gpu/train_gpu.sh needs on a GPU machine that cannot download (run it here,
# where the project's .venv and the MiniLM weights are):
#   .gpu/sim_text_table.npz            the simulated 2D model's class-name embeddings
#   .gpu/val_text_embeddings.npz       the validation's class-name embeddings (data/val's cache)
#   .whl/                              wheels of the packages that such an image lacks (x86-64, py3.12)
# Both folders are ignored by git (.gitignore) and must travel with the command (carried).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
"$PY" scripts/gpu/record.py --write-table .gpu/sim_text_table.npz
"$PY" - <<'PYEOF'
from pathlib import Path
from mapper.training.train import class_text_embeddings
from clients.sim.scenes import CLASS_NAMES
import shutil
val = Path(".gpu/val")
val.mkdir(parents=True, exist_ok=True)
class_text_embeddings(val, list(CLASS_NAMES))   # writes val/text_embeddings_minilm-l6-v2.npz
shutil.move(val / "text_embeddings_minilm-l6-v2.npz", ".gpu/val_text_embeddings.npz")
val.rmdir()
print("wrote .gpu/val_text_embeddings.npz")
PYEOF
mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl pyzmq==27.3.0 trimesh==5.2.0 threadpoolctl==3.8.0
ls -la .gpu .whl
