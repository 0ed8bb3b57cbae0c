"""`nd` arrays and images: exact round trips, byte order, copies, and rejections."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.arrays import ND_DTYPES, decode_image, decode_nd, encode_image, encode_nd
from protocol.errors import ProtocolError


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(ND_DTYPES).flatmap(
        lambda dt: hnp.arrays(np.dtype(dt), hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5))
    )
)
def test_nd_round_trip_exact(array: np.ndarray) -> None:
    back = decode_nd(encode_nd(array), field="x")
    assert back.dtype == array.dtype and back.shape == array.shape
    assert back.tobytes() == array.tobytes()  # bit-exact, NaN payloads included


def test_nd_wire_is_little_endian_and_decode_is_native() -> None:
    big = np.arange(6, dtype=">f4").reshape(2, 3)
    wire = encode_nd(big)
    assert wire["dtype"] == "float32" and wire["shape"] == [2, 3]
    assert wire["data"] == np.arange(6, dtype="<f4").tobytes()
    back = decode_nd(wire, field="x")
    assert back.dtype.isnative and np.array_equal(back, big)
    # non-contiguous input is sent in C order
    assert decode_nd(encode_nd(big.T), field="x").tolist() == big.T.tolist()


def test_nd_decode_returns_a_writable_copy() -> None:
    data = bytearray(np.arange(4, dtype=np.int32).tobytes())
    back = decode_nd({"dtype": "int32", "shape": [4], "data": data}, field="x")
    back[0] = 99  # writable
    data[0:4] = b"\x07\x00\x00\x00"
    assert back.tolist() == [99, 1, 2, 3]  # not a view on the message buffer


def test_nd_encode_rejects_non_wire_dtypes() -> None:
    for array in (np.zeros(2, bool), np.zeros(2, np.int64), np.zeros(2, np.complex64)):
        with pytest.raises(TypeError, match="cannot be sent"):
            encode_nd(array)


@pytest.mark.parametrize(
    "obj,kwargs,match",
    [
        ([1, 2], {}, "expected a map"),
        ({"dtype": "float32", "shape": [1]}, {}, "missing 'data'"),
        ({"dtype": "float32", "shape": [1], "data": b"\x00" * 4, 5: 1}, {}, "map keys must be strings"),
        ({"dtype": "float32", "shape": [2], "data": b"\x00" * 4}, {}, "needs 8 bytes"),
        ({"dtype": "float32", "shape": [1] * 9, "data": b"\x00" * 4}, {}, "at most 8 allowed"),
        ({"dtype": "float32", "shape": [2**40, 0], "data": b""}, {}, "shape entries must be ints"),
        ({"dtype": "float32", "shape": [1], "data": b"\x00" * 4}, {"dtypes": ["int32"]}, "expected int32"),
        ({"dtype": "float32", "shape": [1], "data": b"\x00" * 4}, {"ndim": 2}, "expected 2 dimensions"),
        ({"dtype": "float32", "shape": [1, 2], "data": b"\x00" * 8}, {"shape": (1, 3)},
         "dimension 1 must be 3"),
        ({"dtype": 5, "shape": [1], "data": b"\x00"}, {}, "not a wire dtype"),
    ],
)
def test_nd_rejections(obj: object, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ProtocolError, match=match) as info:
        decode_nd(obj, field="xyz", **kwargs)  # type: ignore[arg-type]
    assert info.value.code == "bad_request" and info.value.message.startswith("xyz")


def test_huge_declared_shape_with_zero_bytes_does_not_allocate() -> None:
    back = decode_nd({"dtype": "float64", "shape": [0, 2**31 - 1], "data": b""}, field="x")
    assert back.size == 0 and back.shape == (0, 2**31 - 1)


@pytest.mark.parametrize("encoding", ["rgb8", "png", "jpeg"])
def test_image_round_trip(encoding: str) -> None:
    h, w = 17, 23
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.stack([xx * 10, yy * 12, np.full_like(xx, 200)], axis=-1).astype(np.uint8)
    wire = encode_image(rgb, encoding, jpeg_quality=95)
    assert wire["encoding"] == encoding
    back = decode_image(wire, width=w, height=h)
    assert back.shape == (h, w, 3) and back.dtype == np.uint8 and back.flags.writeable
    if encoding == "jpeg":
        assert np.abs(back.astype(int) - rgb.astype(int)).mean() < 3  # channel order kept: R, G, B
    else:
        assert np.array_equal(back, rgb)


def test_image_encode_rejections() -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        encode_image(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        encode_image(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="unknown image encoding"):
        encode_image(np.zeros((4, 4, 3), np.uint8), "webp")
    with pytest.raises(ValueError, match="jpeg_quality"):
        encode_image(np.zeros((4, 4, 3), np.uint8), "jpeg", jpeg_quality=101)


def test_image_decode_size_check() -> None:
    wire = encode_image(np.zeros((4, 5, 3), np.uint8), "png")
    with pytest.raises(ProtocolError, match="png image is 5x4 but the message says 4x5"):
        decode_image(wire, width=4, height=5, field="rgb")


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_all_finite_matches_numpy_for_every_special_value(dtype: type) -> None:
    """The feature maps' finite check (float16 by its exponent bits) against ``np.isfinite``: the
    largest, smallest and subnormal values pass, Inf, -Inf and NaN (any payload) fail, strided too."""
    from protocol.messages import all_finite

    info = np.finfo(dtype)
    base = np.random.default_rng(0).standard_normal((6, 8, 5)).astype(dtype)
    for value in (info.max, -info.max, info.tiny, info.tiny / 4, -0.0, np.inf, -np.inf, np.nan):
        arr = base.copy()
        arr[2, 3, 1] = value
        assert all_finite(arr) == bool(np.all(np.isfinite(arr))), value
        assert all_finite(arr[:, ::2]) == bool(np.all(np.isfinite(arr[:, ::2]))), value
    if dtype is np.float16:
        bits = np.arange(1 << 16, dtype=np.uint16).view(np.float16)  # every half float, NaN payloads too
        for chunk in np.split(bits, 256):
            assert all_finite(chunk.reshape(1, 1, -1)) == bool(np.all(np.isfinite(chunk)))
