"""``govnesf evaluate --rgb-only-node`` (mapper.training.eval_node): a tiny generated scene streamed
without depth through an in-process node with the plugins ``govnesf serve`` installs, its
``segment_points`` answers scored against the ground truth."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import pytest

from mapper.model.checkpoint import save_checkpoint
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from mapper.training import evaluate as ev
from mapper.training.eval_node import NODE_ROWS
from tests.mapper.training.test_evaluate import D, make_scene, text_embeddings, tiny_model

SPACE = "test-onehot-8"


class OneHotText:
    """The test scene's class embeddings as a text encoder: ``classI`` -> row I."""

    space = SPACE
    dim = D

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Other texts (the node's warm-up "chair") get the last class's row (never an answer)."""
        emb = text_embeddings().numpy()
        rows = [int(t[5:]) if t.startswith("class") and t[5:].isdigit() else len(emb) - 1 for t in texts]
        return emb[rows].astype(np.float32)


@pytest.fixture()
def space() -> Iterator[str]:
    register_text_encoder(SPACE, OneHotText)
    yield SPACE
    unregister_text_encoder(SPACE)


@pytest.mark.slow  # ~8 s alone: a node with the model, triangulation and rendered depth
def test_node_rows_stream_the_scene_without_depth_and_score_every_point(tmp_path, space: str) -> None:
    scene = make_scene()
    ckpt = str(save_checkpoint(tmp_path / "tiny", tiny_model(), metadata={"preset": "tiny", "step": 0}))
    settings = ev.EvalSettings(do_2d=False, oracle=False, no_depth_input=False, rgb_only_node=ckpt,
                               node_ov_space=space)
    lines: list[str] = []
    res = ev.evaluate_scene(scene, {}, text_embeddings(), settings, log=lines.append)["3d"]
    gt = scene.points_label
    for name in NODE_ROWS.values():
        r = res[name]
        assert int(r.cm.sum()) == len(gt)  # every evaluated point scored (unanswered ones as wrong)
        assert r.extra["keyframes"] >= 2 and r.extra["stream_seconds"] > 0
        assert any(name in line for line in lines)
    # the window's plain average of the streamed (exact) features labels the floor regions
    assert res["Node RGB-only: average"].scores().oacc >= 0.9
