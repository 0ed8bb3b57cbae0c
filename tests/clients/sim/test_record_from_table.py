"""scripts/gpu/record.py: a recording whose class-name embeddings come from a table (a machine
without the MiniLM weights) has the same OV maps as one that embeds them with the model."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]


def _load_script():
    spec = importlib.util.spec_from_file_location("gpu_record", ROOT / "scripts" / "gpu" / "record.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_table_recording_equals_model_recording(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    script = _load_script()
    table = tmp_path / "table.npz"
    script.write_table(table)
    enc = script._TableEncoder(table)
    texts = script.sim_texts()
    assert enc.encode(texts).shape == (len(texts), 384)
    with pytest.raises(KeyError, match="not in the embedding table"):
        enc.encode(["a text the simulator never embeds"])

    import clients.sim.text as text
    from clients.sim.cli import main as sim_main
    from mapper.training.data import load_scene

    args = ["record", "--seed", "3", "--frames", "2", "--width", "64", "--height", "48", "--depth", "--quiet"]
    assert sim_main([*args, "--out", str(tmp_path / "model")]) == 0
    monkeypatch.setattr(text, "_DEFAULT", enc)
    argv = ["record.py", "--table", str(table), "--", *args, "--out", str(tmp_path / "t")]
    monkeypatch.setattr(sys, "argv", argv)
    assert script.main() == 0
    a, b = load_scene(tmp_path / "model"), load_scene(tmp_path / "t")
    assert np.array_equal(a.ov, b.ov) and np.array_equal(a.rgb, b.rgb)
