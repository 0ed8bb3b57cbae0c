"""Wire encodings of n-d arrays (`nd`) and images, with strict validation on decode.

`nd` on the wire: ``{"dtype": str, "shape": [int, ...], "data": bin}``, little-endian, C order,
``len(data) == prod(shape) * itemsize``. Images: ``{"encoding": "rgb8"|"jpeg"|"png", "data": bin}``.

Decoding never trusts a declared size beyond what the bytes actually hold: `nd` shapes must
match the byte length exactly, and compressed images have their header size checked against
the enclosing message's width/height *before* the pixels are decompressed.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np

from protocol.errors import ProtocolError

ND_DTYPES: tuple[str, ...] = ("uint8", "uint16", "int32", "float16", "float32", "float64")
"""dtype names allowed in an `nd` array on the wire."""

IMAGE_ENCODINGS: tuple[str, ...] = ("rgb8", "jpeg", "png")
"""Image encodings allowed on the wire."""

MAX_ND_NDIM = 8
"""Most dimensions an `nd` array may declare."""

MAX_ND_DIM = 2**31 - 1
"""Largest single dimension an `nd` array may declare (sizes are also bounded by the byte length)."""

_WIRE_DTYPE: dict[str, np.dtype[Any]] = {name: np.dtype(name).newbyteorder("<") for name in ND_DTYPES}


def _bad(field: str, what: str) -> ProtocolError:
    return ProtocolError("bad_request", f"{field}: {what}")


def _as_bytes(obj: Any, field: str) -> bytes:
    if isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj) if not isinstance(obj, bytes) else obj
    raise _bad(field, f"expected binary data (msgpack bin), got {type(obj).__name__}")


def _as_str_keyed_map(obj: Any, field: str) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise _bad(field, f"expected a map, got {type(obj).__name__}")
    for key in obj:
        if not isinstance(key, str):
            raise _bad(field, f"map keys must be strings, got {type(key).__name__} {key!r:.40}")
    return obj


def encode_nd(array: np.ndarray) -> dict[str, Any]:
    """Encode an array as a wire `nd` map: little-endian, C order.

    Args:
        array: any shape; dtype one of `ND_DTYPES` (bool and 64-bit ints are not wire types).
    Returns:
        ``{"dtype": str, "shape": list[int], "data": bytes}``.
    Raises:
        TypeError: the dtype has no wire representation (a programming error on the sender).
    """
    array = np.asarray(array)
    name = array.dtype.name
    if name not in _WIRE_DTYPE or array.dtype.kind == "b":
        raise TypeError(f"dtype {array.dtype} cannot be sent; wire dtypes: {', '.join(ND_DTYPES)}")
    wire = array.astype(_WIRE_DTYPE[name], order="C", copy=False)  # keeps 0-d arrays 0-d
    return {"dtype": name, "shape": [int(n) for n in array.shape], "data": wire.tobytes(order="C")}


def decode_nd(
    obj: Any,
    *,
    field: str,
    dtypes: Collection[str] | None = None,
    ndim: int | None = None,
    shape: Sequence[int | None] | None = None,
) -> np.ndarray:
    """Decode and validate a wire `nd` map.

    Args:
        obj: the wire value.
        field: name used in error messages (e.g. ``"depth"``).
        dtypes: allowed dtype names (default: any of `ND_DTYPES`).
        ndim: required number of dimensions (implied by `shape` when that is given).
        shape: required shape; ``None`` entries match any size.
    Returns:
        A writable, native-endian, C-contiguous copy (never a view on the message buffer).
    Raises:
        ProtocolError("bad_request"): wrong type, dtype, shape or byte length.
    """
    m = _as_str_keyed_map(obj, field)
    for key in ("dtype", "shape", "data"):
        if key not in m:
            raise _bad(field, f"nd array is missing {key!r} (needs dtype, shape, data)")
    dtype_name = m["dtype"]
    allowed = tuple(dtypes) if dtypes is not None else ND_DTYPES
    if not isinstance(dtype_name, str) or dtype_name not in _WIRE_DTYPE:
        raise _bad(field, f"dtype {dtype_name!r:.40} is not a wire dtype ({', '.join(ND_DTYPES)})")
    if dtype_name not in allowed:
        raise _bad(field, f"dtype {dtype_name} not allowed here; expected {' or '.join(allowed)}")
    dims = m["shape"]
    if not isinstance(dims, list | tuple):
        raise _bad(field, f"shape must be a list of ints, got {type(dims).__name__}")
    if len(dims) > MAX_ND_NDIM:
        raise _bad(field, f"shape has {len(dims)} dimensions, at most {MAX_ND_NDIM} allowed")
    for n in dims:
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= MAX_ND_DIM:
            raise _bad(field, f"shape entries must be ints in 0..{MAX_ND_DIM}, got {n!r:.40}")
    want_ndim = len(shape) if shape is not None else ndim
    if want_ndim is not None and len(dims) != want_ndim:
        raise _bad(field, f"expected {want_ndim} dimensions, got shape {list(dims)}")
    if shape is not None:
        for i, (got, want) in enumerate(zip(dims, shape, strict=True)):
            if want is not None and got != want:
                raise _bad(field, f"dimension {i} must be {want}, got shape {list(dims)}")
    data = _as_bytes(m["data"], f"{field}.data")
    wire_dtype = _WIRE_DTYPE[dtype_name]
    expected = math.prod(dims) * wire_dtype.itemsize  # Python ints: no overflow
    if len(data) != expected:
        raise _bad(
            field,
            f"data is {len(data)} bytes but shape {list(dims)} x {dtype_name} needs {expected} bytes",
        )
    flat = np.frombuffer(data, dtype=wire_dtype)
    out = flat.astype(wire_dtype.newbyteorder("="), copy=True).reshape(tuple(dims))
    return out


def encode_image(rgb: np.ndarray, encoding: str = "rgb8", *, jpeg_quality: int = 90) -> dict[str, Any]:
    """Encode an RGB image for the wire.

    Args:
        rgb: (H, W, 3) uint8, channels R, G, B.
        encoding: ``"rgb8"`` (raw, lossless), ``"png"`` (lossless) or ``"jpeg"`` (lossy).
        jpeg_quality: 0..100, used for ``"jpeg"`` only.
    Returns:
        ``{"encoding": str, "data": bytes}``.
    Raises:
        ValueError: bad image shape/dtype, unknown encoding, or the encoder failed.
    """
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        desc = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise ValueError(f"image must be an (H, W, 3) uint8 array, got {desc}")
    if encoding == "rgb8":
        return {"encoding": "rgb8", "data": np.ascontiguousarray(rgb).tobytes(order="C")}
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"unknown image encoding {encoding!r}; allowed: {', '.join(IMAGE_ENCODINGS)}")
    if not 0 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality {jpeg_quality} out of range 0..100")
    import cv2  # a core dependency, loaded on the first compressed image (`import protocol` stays light)

    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    if encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ValueError(f"OpenCV failed to encode a {rgb.shape} image as {encoding}")
    return {"encoding": encoding, "data": buf.tobytes()}


def _png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR chunk, or None if the header is not a PNG."""
    if len(data) < 24 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the first JPEG start-of-frame marker, or None if none is found."""
    if len(data) < 4 or data[0] != 0xFF or data[1] != 0xD8:
        return None
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        seg_len = (data[i + 2] << 8) | data[i + 3]
        if seg_len < 2:
            return None
        if marker in _JPEG_SOF:
            if i + 9 > n:
                return None
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(width), int(height)
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any SOF
            return None
        i += 2 + seg_len
    return None


def decode_image(obj: Any, *, width: int, height: int, field: str = "rgb") -> np.ndarray:
    """Decode and validate a wire image.

    Args:
        obj: the wire value ``{"encoding", "data"}``.
        width, height: the size the enclosing message declares, pixels.
        field: name used in error messages.
    Returns:
        (height, width, 3) uint8 RGB, a fresh writable array.
    Raises:
        ProtocolError("bad_request"): unknown encoding, undecodable data, or another size.
    """
    m = _as_str_keyed_map(obj, field)
    for key in ("encoding", "data"):
        if key not in m:
            raise _bad(field, f"image is missing {key!r} (needs encoding, data)")
    encoding = m["encoding"]
    if not isinstance(encoding, str) or encoding not in IMAGE_ENCODINGS:
        raise _bad(field, f"encoding {encoding!r:.40} unknown; allowed: {', '.join(IMAGE_ENCODINGS)}")
    data = _as_bytes(m["data"], f"{field}.data")
    if encoding == "rgb8":
        expected = width * height * 3
        if len(data) != expected:
            raise _bad(
                field, f"rgb8 data is {len(data)} bytes but {width}x{height}x3 needs {expected} bytes"
            )
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3).copy()
    # Check the declared size before decompressing, so a tiny hostile file cannot make the
    # decoder allocate a huge image.
    size = _png_size(data) if encoding == "png" else _jpeg_size(data)
    if size is None:
        raise _bad(field, f"data is not a decodable {encoding} image ({len(data)} bytes)")
    if size != (width, height):
        raise _bad(field, f"{encoding} image is {size[0]}x{size[1]} but the message says {width}x{height}")
    import cv2  # a core dependency, loaded on the first compressed image

    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    except cv2.error as exc:  # pragma: no cover - OpenCV usually returns None instead
        raise _bad(field, f"data is not a decodable {encoding} image: {exc}") from None
    if bgr is None:
        raise _bad(field, f"data is not a decodable {encoding} image ({len(data)} bytes)")
    if bgr.shape[:2] != (height, width) or bgr.ndim != 3 or bgr.shape[2] != 3:
        raise _bad(field, f"decoded image has shape {bgr.shape}, expected ({height}, {width}, 3)")
    if bgr.dtype != np.uint8:
        raise _bad(field, f"decoded image has dtype {bgr.dtype}, expected 8-bit channels")
    return np.ascontiguousarray(bgr[:, :, ::-1])
