"""PLY output of ``govnesf query --out`` (clients/ply.py): float32 xyz, a float32 ``score``
property and a colour by score, read back byte for byte, by Open3D's tensor I/O (skipped when
open3d is not installed) and through the CLI against a scripted query endpoint, including the
empty answer (a valid PLY with 0 points, not an error)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from clients.cli import query as query_cli
from clients.colors import score_colours
from clients.ply import PLY_VERTEX_DTYPE, PlyError, read_points_ply, write_points_ply
from protocol.messages import ObjectCandidate, Points, QueryPoints
from tests.node_helpers import ScriptedQueryEndpoint


def _cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    score = rng.uniform(0.1, 0.4, n).astype(np.float32)
    return xyz, score


def test_points_round_trip_as_float32_with_score_and_colour(tmp_path: Path) -> None:
    xyz, score = _cloud(50)
    path = write_points_ply(tmp_path / "sub" / "a.ply", xyz, score)  # creates the folder
    assert path == tmp_path / "sub" / "a.ply" and not (tmp_path / "sub" / "a.ply.partial").exists()
    data = path.read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode("ascii")
    assert "format binary_little_endian 1.0" in header and "element vertex 50" in header
    props = [line.split()[1:] for line in header.splitlines() if line.startswith("property")]
    assert props == [["float", "x"], ["float", "y"], ["float", "z"], ["float", "score"],
                     ["uchar", "red"], ["uchar", "green"], ["uchar", "blue"]]  # fmt: skip
    assert len(data) == len(header) + 50 * 19
    back = read_points_ply(path)
    assert back.dtype == PLY_VERTEX_DTYPE
    np.testing.assert_array_equal(np.stack([back["x"], back["y"], back["z"]], 1), xyz)
    np.testing.assert_array_equal(back["score"], score)
    rgb = np.stack([back["red"], back["green"], back["blue"]], 1)
    np.testing.assert_array_equal(rgb, np.rint(score_colours(score) * 255).astype(np.uint8))
    lowest, highest = int(np.argmin(score)), int(np.argmax(score))
    assert rgb[lowest].tolist() == [68, 1, 84] and rgb[highest].tolist() == [253, 231, 37]  # viridis ends


def test_open3d_tensor_io_reads_the_score_attribute(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    xyz, score = _cloud(20, seed=1)
    path = write_points_ply(tmp_path / "a.ply", xyz, score)
    cloud = o3d.t.io.read_point_cloud(str(path))
    positions = cloud.point.positions.numpy()
    assert positions.dtype == np.float32
    np.testing.assert_array_equal(positions, xyz)
    read_score = cloud.point.score.numpy()
    assert read_score.dtype == np.float32 and read_score.shape == (20, 1)
    np.testing.assert_array_equal(read_score[:, 0], score)
    assert cloud.point.colors.numpy().shape == (20, 3)
    legacy = o3d.io.read_point_cloud(str(path))  # the legacy reader keeps points and colours
    assert len(legacy.points) == 20 and legacy.has_colors()


def test_empty_answer_is_a_valid_empty_ply(tmp_path: Path) -> None:
    path = write_points_ply(tmp_path / "e.ply", np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    assert b"element vertex 0\n" in path.read_bytes() and path.read_bytes().endswith(b"end_header\n")
    assert read_points_ply(path).shape == (0,)
    try:
        import open3d as o3d
    except ImportError:
        return
    cloud = o3d.t.io.read_point_cloud(str(path))
    assert cloud.point.positions.shape == o3d.core.SizeVector([0, 3])
    assert "score" in cloud.point


@pytest.mark.parametrize(
    ("xyz", "score", "fragment"),
    [
        (np.zeros((3, 2)), np.zeros(3), "xyz must be (N, 3)"),
        (np.zeros((3, 3)), np.zeros(4), "score must be (3,)"),
        (np.array([[0.0, np.nan, 0.0]]), np.zeros(1), "xyz has 1 non-finite"),
        (np.zeros((2, 3)), np.array([0.1, np.inf]), "score has 1 non-finite"),
    ],
)
def test_bad_points_are_refused_and_nothing_is_written(
    tmp_path: Path, xyz: np.ndarray, score: np.ndarray, fragment: str
) -> None:
    with pytest.raises(PlyError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        write_points_ply(tmp_path / "bad.ply", xyz, score)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_path_is_an_oserror_naming_it(tmp_path: Path) -> None:
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(OSError, match="dir.ply"):
        write_points_ply(tmp_path / "dir.ply", *_cloud(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.ply"]


class ScriptedQueryNode(ScriptedQueryEndpoint[QueryPoints]):
    """A query endpoint on a free TCP port that answers every ``query_points`` with ``answer``."""

    def __init__(self, answer: Points) -> None:
        super().__init__(QueryPoints, answer)


def _query(answer: Points, out: Path) -> int:
    server = ScriptedQueryNode(answer)
    try:
        args = ["chair", "--query", server.endpoint, "--timeout", "10", "--out", str(out)]
        return query_cli.query_main(args)
    finally:
        server.close()


def test_query_cli_writes_scores_and_an_empty_answer(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    xyz, score = _cloud(8, seed=2)
    obj = ObjectCandidate(text="chair", centroid=xyz.mean(0), aabb_min=xyz.min(0), aabb_max=xyz.max(0),
                          score=float(score.max()), n_points=8)  # fmt: skip
    answer = Points(map_version=3, xyz=xyz, score=score, label=np.zeros(8, np.int32), objects=[obj])
    assert _query(answer, tmp_path / "chair.ply") == 0
    back = read_points_ply(tmp_path / "chair.ply")
    np.testing.assert_array_equal(back["score"], score)
    assert f"wrote {tmp_path / 'chair.ply'}\n" in capsys.readouterr().out

    empty = Points(map_version=3, xyz=np.zeros((0, 3), np.float32), score=np.zeros(0, np.float32),
                   label=np.zeros(0, np.int32))  # fmt: skip
    assert _query(empty, tmp_path / "none.ply") == 0
    assert read_points_ply(tmp_path / "none.ply").shape == (0,)
    assert "no points matched: a valid PLY with 0 points" in capsys.readouterr().out

    (tmp_path / "taken.ply").mkdir()  # an unwritable --out: exit 1 with the path, no traceback
    assert _query(answer, tmp_path / "taken.ply") == 1
    assert "cannot write --out" in capsys.readouterr().err and (tmp_path / "taken.ply").is_dir()
