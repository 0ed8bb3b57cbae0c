"""Write synthetic ``.govmap`` files of a given number of global-map points, for ``govnesf bench``.

The bench (``clients/cli/bench.py``) is a client: it cannot build a map file itself, so it runs
this module (``python -m mapper.bench.synthetic_maps``, with the node's Python; it ships in the
package, so an installed ``govnesf`` runs it too) to put maps into the node's map directory and
``load`` them. Each map is ``N`` points on a grid at the voxel size (one point per voxel, so
the voxel keys are unique), with 384-d fp16 features in the ``minilm-l6-v2`` space: the embedding
of one of a few class names per 0.5 m block plus noise, normalised. No keyframes.

    .venv/bin/python -m mapper.bench.synthetic_maps MAP_DIR 10000 100000 1000000   # -> points_<N>.govmap
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

CLASSES = ("chair", "table", "sofa", "bed", "floor", "wall", "lamp", "plant")


def synthetic_map(n: int, voxel_size_m: float = 0.05, seed: int = 0) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, manifest) of a map with ``n`` points, in the node's map-file layout."""
    from mapper.map.global_map import voxel_keys
    from mapper.ov.encoders import SPACE, get_text_encoder

    rng = np.random.default_rng(seed)
    side = int(np.ceil(n ** (1 / 3)))
    idx = np.stack(np.unravel_index(np.arange(n), (side, side, side)), axis=1)
    xyz = ((idx + 0.5) * voxel_size_m).astype(np.float32)
    keys, ok = voxel_keys(xyz, voxel_size_m)
    assert ok.all() and np.unique(keys).size == n
    emb = get_text_encoder(SPACE).encode(list(CLASSES))  # (C, 384)
    block = np.floor(xyz / 0.5).astype(np.int64)
    cls = (block[:, 0] * 7 + block[:, 1] * 3 + block[:, 2]) % len(CLASSES)
    feat = np.empty((n, emb.shape[1]), np.float16)
    for i in range(0, n, 200_000):  # in chunks: a 1M x 384 float32 temporary would be 1.5 GB
        f = emb[cls[i : i + 200_000]] + 0.05 * rng.standard_normal((min(200_000, n - i), emb.shape[1]))
        f /= np.linalg.norm(f, axis=1, keepdims=True)
        feat[i : i + 200_000] = f.astype(np.float16)
    ones = np.ones(n, np.float32)
    arrays = {
        "global.keys": keys,
        "global.xyz": xyz,
        "global.weight": ones,
        "global.feat_norm": ones,
        "global.feat_weight": ones,
        "global.hits": np.ones(n, np.int32),
        "global.last_seen_ns": np.zeros(n, np.int64),
        "global.age_kf": np.zeros(n, np.int64),
        "global.feat": feat,
    }
    manifest = {
        "map_version": 1,
        "ov_space": SPACE,
        "ov_dim": int(emb.shape[1]),
        "keyframes": [],
        "global_map": {
            "format": "global-map-v1",
            "points": n,
            "dim": int(emb.shape[1]),
            "voxel_size_m": voxel_size_m,
            "map_version": 1,
            "points_pruned": 0,
            "keyframes_integrated": 0,
        },
        "saved_unix_s": 0.0,
        "config": {},
    }
    return arrays, manifest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("map_dir", type=Path)
    parser.add_argument("sizes", nargs="+", type=int, help="points of each map (one map per size, >= 1)")
    parser.add_argument("--voxel-size-m", type=float, default=0.05)
    args = parser.parse_args(argv)
    if min(args.sizes) < 1 or not args.voxel_size_m > 0:
        parser.error(f"sizes must be >= 1 and --voxel-size-m > 0, got {args.sizes} and {args.voxel_size_m}")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the text encoder's weights come from the local cache
    from mapper.node.store import MapStore

    store = MapStore(str(args.map_dir))
    for n in args.sizes:
        arrays, manifest = synthetic_map(n, args.voxel_size_m)
        print(store.save(f"points_{n}", arrays, manifest))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
