"""The text encoders' prompt cache (:class:`mapper.ov.encoders.PromptCache`): bounded, each prompt
embedded once, and cached prompts answered while another request's prompts are being embedded."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from mapper.ov.encoders import PromptCache


class _Embedder:
    def __init__(self, dim: int = 4, gate: threading.Event | None = None) -> None:
        self.dim = dim
        self.calls: list[list[str]] = []
        self.gate = gate
        self.started = threading.Event()

    def __call__(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        self.started.set()
        if self.gate is not None:
            assert self.gate.wait(10.0)
        rows = np.array([[len(t), 1.0, 0.0, 0.0] for t in texts], np.float32)
        return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_each_distinct_prompt_is_embedded_once_and_rows_follow_the_texts() -> None:
    embed = _Embedder()
    cache = PromptCache(embed, 4)
    a = cache.get(["chair", "table", "chair"])
    assert embed.calls == [["chair", "table"]] and a.shape == (3, 4) and a.dtype == np.float32
    np.testing.assert_array_equal(a[0], a[2])
    assert cache.uncached_chars(["chair", "sofa", "sofa", "a bed"]) == len("sofa") + len("a bed")
    b = cache.get(["table", "sofa"])
    assert embed.calls[1] == ["sofa"]
    np.testing.assert_array_equal(b[0], a[1])
    assert cache.get([]).shape == (0, 4)
    with pytest.raises(TypeError, match="pass \\[text\\]"):
        cache.get("chair")
    with pytest.raises(TypeError, match="strings"):
        cache.get(["chair", 3])  # type: ignore[list-item]


def test_the_cache_is_bounded_least_recently_used_first() -> None:
    embed = _Embedder()
    cache = PromptCache(embed, 4, max_entries=3)
    cache.get(["a", "b", "c"])
    cache.get(["a"])  # a is now the most recent
    cache.get(["d"])  # b leaves
    assert len(cache) == 3 and cache.uncached_chars(["a", "b", "c", "d"]) == 1
    rows = cache.get(["e", "f", "g", "h"])  # more in one request than the cache holds: all answered
    assert rows.shape == (4, 4) and len(cache) == 3
    with pytest.raises(ValueError, match="max_entries"):
        PromptCache(embed, 4, max_entries=0)


def test_a_bad_embedding_is_refused_and_nothing_is_cached() -> None:
    cache = PromptCache(lambda texts: np.zeros((len(texts), 3), np.float32), 4)
    with pytest.raises(ValueError, match="expected \\(1, 4\\)"):
        cache.get(["chair"])
    assert len(cache) == 0


def test_cached_prompts_do_not_wait_for_another_requests_embedding() -> None:
    gate = threading.Event()
    embed = _Embedder(gate=gate)
    cache = PromptCache(embed, 4)
    gate.set()
    cache.get(["chair"])
    gate.clear()
    embed.started.clear()
    slow = threading.Thread(target=cache.get, args=(["a very long prompt " * 10],))
    slow.start()
    try:
        assert embed.started.wait(10.0)  # the slow request is inside its embedding now
        assert cache.get(["chair"]).shape == (1, 4)  # answered while that one still embeds
        assert slow.is_alive()
    finally:
        gate.set()
        slow.join(10.0)
    assert not slow.is_alive() and len(cache) == 2
