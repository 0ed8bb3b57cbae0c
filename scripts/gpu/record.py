"""``govnesf sim record`` on a machine without the all-MiniLM-L6-v2 weights (a GPU box that cannot
download): the simulated 2D model's class-name embeddings come from a table written beforehand
on a machine that has them. Any other text fails with a clear error instead of loading a model.

    python scripts/gpu/record.py --write-table .gpu/sim_text_table.npz          # where the model is
    python scripts/gpu/record.py --table .gpu/sim_text_table.npz -- record --seed 0 ...   # elsewhere
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def sim_texts() -> list[str]:
    """Every text the simulated 2D model embeds (its prompt per class and its void text)."""
    from clients.sim.scenes import CLASS_NAMES
    from clients.sim.simlseg import SimLSeg

    return SimLSeg.prompt_texts(CLASS_NAMES)


def write_table(path: Path) -> None:
    from clients.sim.text import get_text_encoder

    texts = sim_texts()
    emb = get_text_encoder().encode(texts)  # (T, 384)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, texts=np.asarray(texts), embeddings=emb.astype(np.float32))
    print(f"wrote {len(texts)} text embeddings to {path}")


class _TableEncoder:
    """A ``TextEncoderLike`` that answers from a table only."""

    def __init__(self, path: Path) -> None:
        with np.load(path) as z:
            texts, emb = [str(t) for t in z["texts"]], z["embeddings"].astype(np.float32)
        self._table = dict(zip(texts, emb, strict=True))

    def encode(self, texts: list[str]) -> np.ndarray:
        missing = [t for t in texts if t not in self._table]
        if missing:
            raise KeyError(f"texts not in the embedding table: {missing[:5]} (rewrite it with --write-table)")
        return np.stack([self._table[t] for t in texts])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--write-table", type=Path, help="write the table of the sim's texts and exit")
    p.add_argument("--table", type=Path, help="embed from this table (no text model needed)")
    p.add_argument("sim_args", nargs=argparse.REMAINDER, help="-- then the `govnesf sim` arguments")
    args = p.parse_args()
    if args.write_table:
        write_table(args.write_table)
        return 0
    if args.table is None:
        p.error("--table or --write-table is required")
    if not args.table.is_file():
        p.error(f"--table {args.table}: no such file (write it with --write-table where the model is)")
    import clients.sim.text as text

    text._DEFAULT = _TableEncoder(args.table)  # type: ignore[assignment]
    from clients.sim.cli import main as sim_main

    sim_args = args.sim_args[1:] if args.sim_args[:1] == ["--"] else args.sim_args
    return sim_main(sim_args)


if __name__ == "__main__":
    raise SystemExit(main())
