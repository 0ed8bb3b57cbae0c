"""The mapper's query text encoders and their registry."""

import numpy as np
import pytest

from mapper.ov import encoders
from mapper.ov.encoders import SPACE, UnknownSpaceError, get_text_encoder, register_text_encoder


@pytest.fixture(scope="session")
def mapper_encoder():
    return get_text_encoder(SPACE)


def test_minilm_queries_unit_norm_384d_deterministic(mapper_encoder):
    assert SPACE == "minilm-l6-v2" and mapper_encoder.space == SPACE and mapper_encoder.dim == 384
    emb = mapper_encoder.encode(["chair", "a chair", "bathtub"])
    assert emb.shape == (3, 384) and emb.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(mapper_encoder.encode(["chair"])[0], emb[0])
    assert emb[0] @ emb[1] > emb[0] @ emb[2] + 0.3
    assert get_text_encoder(SPACE) is mapper_encoder


def test_agrees_with_the_client_side_encoder(mapper_encoder):
    from clients.sim.text import get_text_encoder as client_encoder

    texts = ["sofa", "a place to sit"]
    np.testing.assert_allclose(mapper_encoder.encode(texts), client_encoder().encode(texts), atol=1e-6)


def test_unknown_space_raises_a_clear_error():
    with pytest.raises(UnknownSpaceError, match="openclip:ViT-B-16.*minilm-l6-v2"):
        get_text_encoder("openclip:ViT-B-16")


def test_registry_accepts_new_spaces(monkeypatch):
    monkeypatch.setattr(encoders, "_FACTORIES", dict(encoders._FACTORIES))
    monkeypatch.setattr(encoders, "_INSTANCES", dict(encoders._INSTANCES))

    class Fake:
        space, dim = "fake-3", 3

        def encode(self, texts):
            return np.tile(np.eye(3, dtype=np.float32)[:1], (len(texts), 1))

    register_text_encoder("fake-3", Fake)
    assert "fake-3" in encoders.available_spaces()
    enc = get_text_encoder("fake-3")
    assert enc.encode(["x", "y"]).shape == (2, 3)
    assert get_text_encoder("fake-3") is enc
