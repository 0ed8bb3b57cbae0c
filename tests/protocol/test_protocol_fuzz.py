"""Hostile input: whatever bytes arrive, `decode` returns a valid message or raises ProtocolError."""

from __future__ import annotations

import os
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from protocol_samples import frame_wire, pack, samples

from protocol.errors import ERROR_CODES, ProtocolError
from protocol.messages import Message, decode, encode, peek_id

# PROTOCOL_FUZZ_EXAMPLES=5000 for a longer hunt; the default keeps the suite fast.
SETTINGS = settings(
    max_examples=int(os.environ.get("PROTOCOL_FUZZ_EXAMPLES", "150")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
ENCODED = [encode(m) for m in samples()] + [pack(frame_wire())]


def decode_or_protocol_error(data: bytes) -> None:
    try:
        msg = decode(data, max_bytes=1 << 20)
    except ProtocolError as exc:
        assert exc.code in ERROR_CODES and exc.message
        return
    assert isinstance(msg, Message)
    assert decode(encode(msg)) == msg  # anything accepted re-encodes to itself


@SETTINGS
@given(st.binary(max_size=200))
def test_random_bytes(data: bytes) -> None:
    decode_or_protocol_error(data)
    peek_id(data)  # never raises


@SETTINGS
@given(st.sampled_from(ENCODED), st.data())
def test_mutated_valid_messages(data: bytes, draw: st.DataObject) -> None:
    buf = bytearray(data)
    for _ in range(draw.draw(st.integers(1, 4))):
        op = draw.draw(st.sampled_from(["flip", "cut", "insert"]))
        pos = draw.draw(st.integers(0, max(len(buf) - 1, 0)))
        if op == "flip" and buf:
            buf[pos] ^= 1 << draw.draw(st.integers(0, 7))
        elif op == "cut":
            del buf[pos:]
        else:
            buf[pos:pos] = draw.draw(st.binary(min_size=1, max_size=4))
    decode_or_protocol_error(bytes(buf))


wire_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70).filter(lambda n: -(2**63) <= n < 2**64)
    | st.floats() | st.text(max_size=6) | st.binary(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=10,
)


@SETTINGS
@given(st.sampled_from([m.to_wire() for m in samples()] + [frame_wire()]), st.data())
def test_known_keys_with_random_values(wire: dict[str, Any], draw: st.DataObject) -> None:
    keys = sorted(wire)
    for key in draw.draw(st.lists(st.sampled_from(keys), min_size=1, max_size=3, unique=True)):
        if key in ("v", "type"):
            continue
        wire = {**wire, key: draw.draw(wire_values)}
    decode_or_protocol_error(pack(wire))
