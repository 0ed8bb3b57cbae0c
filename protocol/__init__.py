"""Wire protocol v1 of the govnesf mapper: messages, validation, (de)serialisation, recordings.

The ground floor of the project: imports nothing else from it. The contract is
docs/reference/protocol.md; conventions (frames, units, poses) are in docs/concepts/conventions.md.
"""

from protocol.arrays import decode_image, decode_nd, encode_image, encode_nd
from protocol.errors import ERROR_CODES, ErrorCode, ProtocolError, RemoteError
from protocol.messages import (
    MAX_MESSAGE_BYTES,
    ORTHONORMAL_TOL,
    PROTOCOL_VERSION,
    RENDER_OUTPUTS,
    Ack,
    Error,
    Frame,
    Load,
    MapUpdated,
    Message,
    ObjectCandidate,
    Ok,
    Points,
    QueryPoints,
    RecordingHeader,
    Render,
    RenderResult,
    Save,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    decode_as,
    encode,
    error_reply,
    peek_id,
)
from protocol.recording import RecordingReader, RecordingWriter, read_recording

__all__ = [
    "ERROR_CODES", "MAX_MESSAGE_BYTES", "ORTHONORMAL_TOL", "PROTOCOL_VERSION", "RENDER_OUTPUTS",
    "Ack", "Error", "ErrorCode", "Frame", "Load", "MapUpdated", "Message", "ObjectCandidate", "Ok",
    "Points", "ProtocolError", "QueryPoints", "RecordingHeader", "RecordingReader", "RecordingWriter",
    "RemoteError",
    "Render", "RenderResult", "Save", "SegmentPoints", "Segmentation", "Status", "StatusRequest",
    "decode", "decode_as", "decode_image", "decode_nd", "encode", "encode_image", "encode_nd",
    "error_reply", "peek_id", "read_recording",
]
