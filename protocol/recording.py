"""`.govrec` recordings: a header map followed by `frame` messages exactly as on the wire.

The file is a plain concatenation of msgpack maps: first ``{v: 1, type: "recording",
created_ns, meta}``, then one wire `frame` message per frame. `RecordingReader` streams it
(one message in memory at a time) and yields the frames' raw bytes unchanged, so a replay
sends byte-for-byte what was recorded. A cut-short or corrupt tail stops the iteration with
`truncated=True` and an `error` saying at which byte offset and message index; every complete
frame before it is still yielded.

Examples:
    >>> import tempfile, pathlib
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "empty.govrec"
    >>> with RecordingWriter(path, meta={"scene": "demo"}) as rec:
    ...     pass
    >>> reader = read_recording(path)
    >>> reader.header.meta, list(reader), reader.truncated
    ({'scene': 'demo'}, [], False)
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import msgpack

from protocol.errors import ProtocolError
from protocol.messages import MAX_MESSAGE_BYTES, Frame, RecordingHeader, decode, encode

RECORDING_SUFFIX = ".govrec"
"""Conventional file name suffix of recordings."""

MAX_HEADER_BYTES = 16 * 1024 * 1024
"""Largest recording header accepted, bytes."""

_READ_CHUNK = 1 << 20


def _peek_type(data: bytes) -> Any:
    """The top-level ``type`` value of a msgpack map message, without decoding payloads."""
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(data), 1), strict_map_key=False)
    unpacker.feed(data)
    n = unpacker.read_map_header()
    for _ in range(n):
        key = unpacker.unpack()
        if key == "type":
            return unpacker.unpack()
        unpacker.skip()
    return None


class RecordingWriter:
    """Writes a `.govrec` file: the header at construction, then one frame per `write`.

    Use as a context manager. Each write is flushed, so a crash leaves at worst a truncated last
    frame, which `read_recording` reports and skips.
    """

    def __init__(self, path: str | Path, meta: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.header = RecordingHeader(created_ns=time.time_ns(), meta=dict(meta or {}))
        header_bytes = encode(self.header)  # validates meta before the file is created
        self._file: IO[bytes] | None = open(self.path, "wb")  # closed in close()
        self._file.write(header_bytes)
        self._file.flush()
        self.frames_written = 0
        """Number of frames written so far."""

    def write(self, frame: Frame | bytes) -> None:
        """Append one frame: a `Frame`, or the bytes of an already-encoded wire `frame` message.

        Raises:
            ValueError: the writer is closed, or `frame` bytes are not a msgpack ``frame`` map.
        """
        if self._file is None:
            raise ValueError(f"recording {self.path} is closed")
        if isinstance(frame, Frame):
            data = encode(frame)
        elif isinstance(frame, bytes | bytearray | memoryview):
            data = bytes(frame)
            try:
                type_ = _peek_type(data)
            except Exception as exc:
                raise ValueError(f"bytes are not a msgpack map message: {exc}") from None
            if type_ != Frame.TYPE:
                raise ValueError(f"expected an encoded 'frame' message, got type {type_!r}")
        else:
            raise TypeError(f"write() takes a Frame or bytes, got {type(frame).__name__}")
        self._file.write(data)
        self._file.flush()
        self.frames_written += 1

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


@dataclass
class RecordingReader:
    """A `.govrec` file opened by `read_recording`. Iterating yields each frame's raw wire bytes.

    Each iteration re-reads the file from the first frame and resets `truncated`/`error`.
    """

    path: Path
    """The recording file."""
    header: RecordingHeader
    """The decoded header."""
    header_size: int
    """Byte length of the header (offset of the first frame)."""
    max_bytes: int = MAX_MESSAGE_BYTES
    """Largest single frame message accepted, bytes."""
    truncated: bool = False
    """After an iteration: True if it stopped before the end of the file (cut short or corrupt)."""
    error: str | None = None
    """After an iteration: what stopped it (byte offset, message index, reason), else None."""
    frames_read: int = field(default=0)
    """After an iteration: number of complete frame messages yielded."""

    def __iter__(self) -> Iterator[bytes]:
        """Raw bytes of each frame message in order (send these unchanged to replay)."""
        self.truncated = False
        self.error = None
        self.frames_read = 0
        file_size = self.path.stat().st_size
        with open(self.path, "rb") as scan, open(self.path, "rb") as raw:
            scan.seek(self.header_size)
            unpacker = msgpack.Unpacker(
                scan,
                raw=False,
                read_size=min(_READ_CHUNK, self.max_bytes),
                max_buffer_size=self.max_bytes,
                strict_map_key=False,
            )
            index = 1  # message index in the file; the header is message 0
            while True:
                start = self.header_size + unpacker.tell()
                try:
                    unpacker.skip()
                except msgpack.OutOfData:
                    if start < file_size:
                        self._stop(
                            f"message {index} at byte offset {start} is cut short: the file ends at "
                            f"byte {file_size} ({file_size - start} bytes of an incomplete message)"
                        )
                    return
                except Exception as exc:  # corrupt bytes: FormatError, StackError, BufferFull...
                    self._stop(
                        f"message {index} at byte offset {start} is unreadable "
                        f"({type(exc).__name__}: {exc}); stopping there"
                    )
                    return
                end = self.header_size + unpacker.tell()
                raw.seek(start)
                data = raw.read(end - start)
                try:
                    type_ = _peek_type(data)
                except Exception as exc:
                    self._stop(f"message {index} at byte offset {start} is not a map ({exc})")
                    return
                if type_ != Frame.TYPE:
                    self._stop(f"message {index} at byte offset {start} has type {type_!r}, expected 'frame'")
                    return
                self.frames_read += 1
                yield data
                index += 1

    def _stop(self, error: str) -> None:
        self.truncated = True
        self.error = f"{self.path}: {error}"

    def frames(self) -> Iterator[Frame]:
        """Decoded frames in order.

        Raises:
            ProtocolError: a complete frame message that fails validation (with its index).
        """
        for i, data in enumerate(self):
            try:
                msg = decode(data, max_bytes=self.max_bytes, direction="request")
            except ProtocolError as exc:
                raise ProtocolError(exc.code, f"{self.path}: frame {i}: {exc.message}") from None
            assert isinstance(msg, Frame)
            yield msg


def read_recording(path: str | Path, *, max_bytes: int = MAX_MESSAGE_BYTES) -> RecordingReader:
    """Open a `.govrec` recording and read its header.

    Raises:
        FileNotFoundError: no such file.
        ProtocolError: ``bad_request`` when the header is missing, cut short, corrupt or not a
            ``recording`` message; ``unsupported_version`` when its `v` is not 1.
    """
    path = Path(path)
    with open(path, "rb") as f:
        unpacker = msgpack.Unpacker(
            f, raw=False, read_size=64 * 1024, max_buffer_size=MAX_HEADER_BYTES, strict_map_key=False
        )
        try:
            unpacker.skip()
        except msgpack.OutOfData:
            size = path.stat().st_size
            what = "is empty" if size == 0 else f"ends inside the header ({size} bytes)"
            raise ProtocolError("bad_request", f"{path}: not a recording: the file {what}") from None
        except Exception as exc:
            raise ProtocolError(
                "bad_request", f"{path}: not a recording: corrupt header ({type(exc).__name__}: {exc})"
            ) from None
        header_size = unpacker.tell()
        f.seek(0)
        header_bytes = f.read(header_size)
    try:
        msg = decode(header_bytes, max_bytes=MAX_HEADER_BYTES, direction="any")
    except ProtocolError as exc:
        raise ProtocolError(exc.code, f"{path}: bad recording header: {exc.message}") from None
    if not isinstance(msg, RecordingHeader):
        raise ProtocolError(
            "bad_request",
            f"{path}: not a recording: first message has type {msg.TYPE!r}, expected 'recording'",
        )
    return RecordingReader(path=path, header=msg, header_size=header_size, max_bytes=max_bytes)


