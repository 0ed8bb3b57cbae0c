"""`.govrec` recordings: round trip, truncated tails, corrupt headers and middles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from protocol_samples import frame, pack, rgb_image

from protocol.errors import ProtocolError
from protocol.messages import Ack, Frame, RecordingHeader, encode
from protocol.recording import RecordingWriter, read_recording


def write_recording(path: Path, n: int = 3) -> tuple[list[bytes], int]:
    """Write `n` frames; return their wire bytes and the header size."""
    frames = [encode(frame(seq=i, rgb=rgb_image(seed=i), depth_m=np.full((6, 8), i + 1.0, np.float32)))
              for i in range(n)]
    with RecordingWriter(path, meta={"scene": "unit", "frames": n}) as rec:
        rec.write(frame(seq=0, rgb=rgb_image(seed=0), depth_m=np.full((6, 8), 1.0, np.float32)))
        for data in frames[1:]:
            rec.write(data)
    header_size = len(encode(read_recording(path).header))
    return frames, header_size


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "a.govrec"
    frames, header_size = write_recording(path)
    assert path.stat().st_size == header_size + sum(len(f) for f in frames)
    reader = read_recording(path)
    assert reader.header.meta == {"scene": "unit", "frames": 3}
    assert reader.header.created_ns > 0
    assert list(reader) == frames  # raw bytes, unchanged
    assert not reader.truncated and reader.error is None and reader.frames_read == 3
    decoded = list(reader.frames())
    assert [f.seq for f in decoded] == [0, 1, 2]
    assert all(isinstance(f, Frame) for f in decoded)
    assert decoded[2].depth_m is not None and float(decoded[2].depth_m[0, 0]) == 3.0
    assert list(reader) == frames  # iterating again re-reads the file


def test_header_only(tmp_path: Path) -> None:
    path = tmp_path / "empty.govrec"
    RecordingWriter(path).close()
    reader = read_recording(path)
    assert list(reader) == [] and not reader.truncated and reader.header.meta == {}


def test_truncated_tail_at_several_offsets(tmp_path: Path) -> None:
    path = tmp_path / "a.govrec"
    frames, header_size = write_recording(path)
    full = path.read_bytes()
    starts = np.cumsum([header_size] + [len(f) for f in frames])  # start offset of each frame, and the end
    for k in range(3):  # cut inside frame k, at its first byte, a few bytes in, middle, last byte
        for cut in (starts[k] + 1, starts[k] + 7, (starts[k] + starts[k + 1]) // 2, starts[k + 1] - 1):
            cut_path = tmp_path / f"cut{cut}.govrec"
            cut_path.write_bytes(full[:cut])
            reader = read_recording(cut_path)
            assert list(reader) == frames[:k], (k, cut)
            assert reader.truncated and reader.error is not None
            assert f"message {k + 1} at byte offset {starts[k]}" in reader.error
            assert "cut short" in reader.error
            assert len(list(reader.frames())) == k
    # a cut exactly between messages is a shorter, complete recording
    for k in range(4):
        cut_path = tmp_path / f"whole{k}.govrec"
        cut_path.write_bytes(full[: starts[k]])
        reader = read_recording(cut_path)
        assert list(reader) == frames[:k] and not reader.truncated and reader.error is None


def test_corrupt_middle_stops_with_error(tmp_path: Path) -> None:
    path = tmp_path / "a.govrec"
    frames, header_size = write_recording(path)
    full = path.read_bytes()
    at = header_size + len(frames[0])
    path.write_bytes(full[:at] + b"\xc1" + full[at:])  # 0xc1 is never valid msgpack
    reader = read_recording(path)
    assert list(reader) == frames[:1]
    assert reader.truncated and reader.error is not None and f"byte offset {at}" in reader.error


def test_non_frame_message_in_the_middle(tmp_path: Path) -> None:
    path = tmp_path / "a.govrec"
    frames, _ = write_recording(path, n=1)
    with path.open("ab") as f:
        f.write(encode(Ack(seq=0, status="accepted", map_version=0)))
        f.write(frames[0])
    reader = read_recording(path)
    assert list(reader) == frames
    assert reader.truncated and reader.error is not None and "'ack', expected 'frame'" in reader.error


def test_invalid_frame_in_recording_raises_on_decode(tmp_path: Path) -> None:
    path = tmp_path / "a.govrec"
    with RecordingWriter(path) as rec:
        wire = frame().to_wire()
        wire["width"] = 0
        rec.write(pack(wire))
    reader = read_recording(path)
    assert len(list(reader)) == 1  # raw bytes are passed on as recorded
    with pytest.raises(ProtocolError, match="frame 0: width: 0 out of range"):
        list(reader.frames())


@pytest.mark.parametrize(
    "content,match",
    [
        (b"", "the file is empty"),
        (b"\xc1garbage", "corrupt header"),
        (pack({"v": 1, "type": "recording", "created_ns": 1})[:-3], "ends inside the header"),
        (pack([1, 2, 3]), "message must be a msgpack map"),
        (encode(frame()), "first message has type 'frame', expected 'recording'"),
        (pack({"v": 1, "type": "recording", "created_ns": "yesterday"}), "created_ns: expected an int"),
        (pack({"v": 1, "type": "recording", "created_ns": 1, "meta": [1]}), "meta: expected a map"),
    ],
    ids=["empty", "garbage", "cut-header", "list", "frame-first", "bad-created", "bad-meta"],
)
def test_corrupt_header(tmp_path: Path, content: bytes, match: str) -> None:
    path = tmp_path / "bad.govrec"
    path.write_bytes(content)
    with pytest.raises(ProtocolError, match=match) as info:
        read_recording(path)
    assert info.value.code == "bad_request" and str(path) in info.value.message


def test_header_version(tmp_path: Path) -> None:
    path = tmp_path / "v2.govrec"
    path.write_bytes(pack({"v": 2, "type": "recording", "created_ns": 1, "meta": {}}))
    with pytest.raises(ProtocolError) as info:
        read_recording(path)
    assert info.value.code == "unsupported_version"


def test_writer_rejects_non_frames(tmp_path: Path) -> None:
    path = tmp_path / "w.govrec"
    with RecordingWriter(path) as rec:
        with pytest.raises(ValueError, match="expected an encoded 'frame' message, got type 'ack'"):
            rec.write(encode(Ack(seq=0, status="accepted", map_version=0)))
        with pytest.raises(ValueError, match="not a msgpack map"):
            rec.write(b"\xc1")
        with pytest.raises(TypeError):
            rec.write(RecordingHeader(created_ns=1))  # type: ignore[arg-type]
        assert rec.frames_written == 0
    with pytest.raises(ValueError, match="closed"):
        rec.write(frame())
    rec.close()  # idempotent
    assert list(read_recording(path)) == []
    with pytest.raises(ProtocolError, match="meta"):
        RecordingWriter(tmp_path / "x.govrec", meta={1: "non-str key"})  # type: ignore[dict-item]
    assert not (tmp_path / "x.govrec").exists()
