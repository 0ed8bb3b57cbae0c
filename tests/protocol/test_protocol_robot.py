"""The optional robot name of a `frame`: left out of the wire for the default robot (a frame without
one encodes as before the key existed), round-trips when set, and a bad name is refused with a
message that says what is allowed."""

from __future__ import annotations

import msgpack
import pytest

from protocol.errors import ProtocolError
from protocol.messages import MAX_ROBOT_CHARS, Frame, decode, encode
from tests.protocol.protocol_samples import frame, frame_wire, pack


def test_default_robot_is_not_sent_and_decodes_as_empty() -> None:
    wire = msgpack.unpackb(encode(frame()))
    assert "robot" not in wire
    decoded = decode(encode(frame()), direction="request")
    assert isinstance(decoded, Frame) and decoded.robot == ""
    assert decode(pack(frame_wire(robot="")), direction="request").robot == ""  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", ["r1", "robot_B.left-2", "x" * MAX_ROBOT_CHARS])
def test_robot_name_round_trips(name: str) -> None:
    data = encode(frame(robot=name))
    assert msgpack.unpackb(data)["robot"] == name
    decoded = decode(data, direction="request")
    assert isinstance(decoded, Frame) and decoded.robot == name and decoded == frame(robot=name)


@pytest.mark.parametrize("name", ["a b", "r/1", "é", "x" * (MAX_ROBOT_CHARS + 1), 3, None, ["r"]])
def test_bad_robot_name_is_refused(name: object) -> None:
    if name is None:  # nil counts as absent: the default robot
        assert decode(pack(frame_wire(robot=None)), direction="request").robot == ""  # type: ignore[attr-defined]
        return
    with pytest.raises(ProtocolError) as info:
        decode(pack(frame_wire(robot=name)), direction="request")
    assert info.value.code == "bad_request"
    assert "robot" in info.value.message
    with pytest.raises(ProtocolError):
        frame(robot=name)
