"""The learned handlers on a node with real sockets (in-process): frames streamed by a client,
``segment_points`` (govnesf) and ``render`` over loopback, and ``govnesf render`` writing PNGs.

Uses a tiny random-init model (mechanics, not quality) so it runs in seconds on 2 CPU cores.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from clients.cli import main as govnesf
from clients.client import MapperClient
from mapper.model.field import GovNeSF
from mapper.node.backends.learned import install_learned_backend
from mapper.node.service import MapperNode
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from protocol.errors import RemoteError
from protocol.messages import Frame
from tests.model_helpers import look_at, tiny_model_config
from tests.node_helpers import in_process_node

TINY = tiny_model_config()
SPACE = "e2e-space"


class FakeEncoder:
    space = SPACE
    dim = 4

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        return np.stack([np.eye(4, dtype=np.float32)[len(t) % 4] for t in texts])


def frames(n: int) -> Iterator[Frame]:
    for seq in range(n):
        a = 0.5 * seq
        rng = np.random.default_rng(seq)
        yield Frame(
            seq=seq,
            stamp_ns=seq * 1_000_000,
            width=48,
            height=36,
            K=np.array([38.0, 38.0, 24.0, 18.0]),
            world_from_cam=look_at((2 * np.cos(a), 2 * np.sin(a), 1.2), (0.0, 0.0, 0.5)),
            rgb=rng.integers(0, 256, (36, 48, 3), dtype=np.uint8),
            depth_m=np.full((36, 48), 2.0, np.float32),
            ov=np.broadcast_to(np.eye(4, dtype=np.float32)[1], (6, 8, 4)).copy(),  # every view says len 1
            ov_space=SPACE,
        )


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    mapper = in_process_node(tmp_path, autosave_name="", window={"max_keyframes": 4})
    torch.manual_seed(0)
    runtime = ModelRuntime(
        ModelRuntimeConfig(device="cpu"), model=GovNeSF(TINY).eval(), text_encoder=lambda space: FakeEncoder()
    )
    install_learned_backend(mapper, runtime)
    mapper.start()
    try:
        yield mapper
    finally:
        mapper.stop()


def test_stream_then_segment_and_render_over_loopback(node: MapperNode, tmp_path: Path) -> None:
    with MapperClient(
        node.config.ingest_endpoint, node.config.query_endpoint, timeout_s=60.0, retries=0
    ) as client:
        with pytest.raises(RemoteError) as info:
            client.segment_points(np.zeros((1, 3), np.float32), ["x"])
        assert info.value.code == "not_ready"
        acks = list(client.send_frames(frames(6)))
        assert [getattr(r.reply, "status", None) for r in acks] == ["keyframe"] * 6
        xyz = np.array([[0.0, 0.0, 0.5], [0.1, 0.1, 0.6], [0.0, 0.0, 50.0]], np.float32)
        seg = client.segment_points(xyz, ["a", "bb"])
        assert seg.label.tolist() == [0, 0, -1]  # every view's feature is text 0's embedding
        assert np.allclose(seg.score[:2], 1.0, atol=1e-4)
        pose = look_at((2.2, 0.3, 1.1), (0.0, 0.0, 0.5))
        result = client.render(
            16, 12, np.array([14.0, 14.0, 8.0, 6.0]), pose, ["rgb", "depth", "label"], ["a", "bb"]
        )
        assert result.rgb is not None and result.rgb.shape == (12, 16, 3)
        assert result.label is not None and set(np.unique(result.label)) <= {-1, 0}
    out = tmp_path / "views" / "view.png"
    npz = str(tmp_path / "view.npz")
    code = govnesf(
        ["render", "--pose", "2.2,0.3,1.1,180,-10", "--width", "16", "--height", "12", "--texts", "a", "bb"]
        + ["--out", str(out), "--separate", "--npz", npz, "--query", node.config.query_endpoint]
    )
    assert code == 0
    combined = np.asarray(Image.open(out))
    assert combined.shape[0] >= 12 and combined.shape[1] >= 3 * 16  # colour | depth | labels (+ legend)
    for name in ("rgb", "depth", "label"):
        assert np.asarray(Image.open(out.with_name(f"view_{name}.png"))).shape == (12, 16, 3)
    arrays = np.load(tmp_path / "view.npz")
    assert arrays["depth_m"].shape == (12, 16) and arrays["score"].shape == (12, 16, 2)


def test_render_cli_reports_bad_arguments_and_refusals(node: MapperNode, tmp_path: Path) -> None:
    endpoint = node.config.query_endpoint
    assert govnesf(["render", "--pose", "1,2,3", "--query", endpoint]) == 2  # 3 numbers, not 5
    assert govnesf(["render", "--pose", "0,0,1,0,90", "--query", endpoint]) == 2  # pitch out of range
    out = str(tmp_path / "v.png")
    assert (
        govnesf(["render", "--pose", "0,0,1,0,0", "--out", out, "--query", endpoint]) == 3
    )  # no keyframes yet
