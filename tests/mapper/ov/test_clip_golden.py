"""The CLIP backend (mapper/ov/clip.py) against golden outputs of the upstream implementation.

``tests/data/clip_golden*`` were computed once by ``scripts/make_clip_golden.py`` with Hugging Face
``transformers``' ``CLIPModel``, ``CLIPTokenizer`` and ``CLIPImageProcessorPil`` on a tiny random
CLIP (width 64, 2 heads, 2 layers per tower, patch 8 on 32 px, embedding 32, context 16); the
weights are stored in the OpenAI / open_clip layout our backend loads. This test needs neither
``transformers`` nor network access: it loads those weights through :class:`ClipDenseBackend` and
compares token ids exactly and embeddings within 1e-5 (float32 on CPU).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import load_file

from mapper.ov.clip import ClipBackendConfig, ClipDenseBackend

DATA = Path(__file__).resolve().parents[2] / "data"
WEIGHTS = DATA / "clip_golden.safetensors"
REF = DATA / "clip_golden_ref.safetensors"
BPE = DATA / "clip_golden_bpe.txt.gz"
ATOL = 1e-5


@pytest.fixture(scope="module")
def golden() -> dict:
    with safe_open(str(REF), "pt") as f:
        meta = f.metadata()
    return {"meta": meta, "texts": json.loads(meta["texts"]), **load_file(str(REF))}


def _backend(golden: dict, **kw) -> ClipDenseBackend:
    meta = golden["meta"]
    kw.setdefault("activation", meta["activation"])
    return ClipDenseBackend(ClipBackendConfig(
        weights_path=str(WEIGHTS), bpe_path=str(BPE), device="cpu",
        text_heads=int(meta["text_heads"]), vision_heads=int(meta["vision_heads"]), **kw,
    ))  # fmt: skip


@pytest.fixture(scope="module")
def backend(golden: dict) -> ClipDenseBackend:
    return _backend(golden)


def test_golden_files_are_small_and_from_upstream(golden: dict) -> None:
    total = sum(p.stat().st_size for p in (WEIGHTS, REF, BPE))
    assert total < 1_000_000, total
    assert golden["meta"]["generator"] == "scripts/make_clip_golden.py" and golden["meta"]["transformers"]


def test_tokens_match_the_upstream_tokenizer(golden: dict, backend: ClipDenseBackend) -> None:
    ours = backend.tokenizer.tokenize(golden["texts"])
    np.testing.assert_array_equal(ours, golden["tokens"].numpy())


def test_text_embeddings_match(golden: dict, backend: ClipDenseBackend) -> None:
    emb = backend.encode_text(golden["texts"])
    assert emb.dtype == np.float32 and emb.shape == tuple(golden["text_embeds"].shape)
    np.testing.assert_allclose(emb, golden["text_embeds"].numpy(), atol=ATOL, rtol=0)


def test_image_embedding_matches(golden: dict, backend: ClipDenseBackend) -> None:
    image = golden["image"].numpy()
    assert image.shape == (backend.arch.image_size, backend.arch.image_size, 3)  # no resize, no crop
    emb = backend.encode_image(image)
    np.testing.assert_allclose(emb, golden["image_embeds"].numpy()[0], atol=ATOL, rtol=0)


@pytest.mark.parametrize("key", ["image", "wide"])
def test_dense_features_match(golden: dict, backend: ClipDenseBackend, key: str) -> None:
    rgb = golden[key].numpy()
    want = golden[f"dense_{'square' if key == 'image' else 'wide'}"].numpy()  # (h_p, w_p, D)
    assert backend.dense_grid(*rgb.shape[:2]) == want.shape[:2]  # the image is used at its own size
    # float32 through the backend's own preprocessing and MaskCLIP path
    with torch.inference_mode():
        pixels = backend._normalise(backend._to_tensor(rgb))
        feats = F.normalize(backend.model.visual.dense(pixels)[0].float(), dim=-1).numpy()
    np.testing.assert_allclose(feats, want, atol=ATOL, rtol=0)
    # the public float16 output: the same within float16 rounding
    np.testing.assert_allclose(backend.dense_features(rgb).astype(np.float32), want, atol=1e-3, rtol=0)


def test_wrong_activation_does_not_match(golden: dict) -> None:
    """The comparison is sharp enough to see the activation (gelu vs quick_gelu)."""
    wrong = "gelu" if golden["meta"]["activation"] == "quick_gelu" else "quick_gelu"
    other = _backend(golden, activation=wrong)
    diff = np.abs(other.encode_text(golden["texts"]) - golden["text_embeds"].numpy()).max()
    assert diff > 100 * ATOL
