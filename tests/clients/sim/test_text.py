"""Client-side text encoder for the minilm-l6-v2 space (loads the real offline model)."""

import numpy as np
import pytest

from clients.sim.text import EMBED_DIM, SPACE, TextEncoder, get_text_encoder


@pytest.fixture(scope="session")
def client_encoder() -> TextEncoder:
    return get_text_encoder()


def test_embeddings_are_unit_norm_384d_float32(client_encoder):
    emb = client_encoder.encode(["chair", "a place to sit", "shower curtain"])
    assert SPACE == "minilm-l6-v2"
    assert emb.shape == (3, EMBED_DIM) == (3, 384)
    assert emb.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)


def test_deterministic_and_cached(client_encoder):
    a = client_encoder.encode(["chair", "bathtub"])
    b = client_encoder.encode(["bathtub", "chair", "chair"])
    np.testing.assert_array_equal(a[0], b[1])
    np.testing.assert_array_equal(a[0], b[2])
    np.testing.assert_array_equal(a[1], b[0])
    assert get_text_encoder() is client_encoder


def test_semantics_chair_closer_to_a_chair_than_to_bathtub(client_encoder):
    chair, a_chair, bathtub = client_encoder.encode(["chair", "a chair", "bathtub"])
    assert chair @ a_chair > chair @ bathtub + 0.3


def test_bad_input_is_rejected(client_encoder):
    with pytest.raises(TypeError, match="pass \\[text\\]"):
        client_encoder.encode("chair")
    with pytest.raises(TypeError, match="strings"):
        client_encoder.encode(["chair", 3])
    assert client_encoder.encode([]).shape == (0, 384)
