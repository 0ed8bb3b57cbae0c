"""Protocol error type: every rejection of wire input is a `ProtocolError` with a wire error code."""

from __future__ import annotations

from typing import Any, Literal, get_args

ErrorCode = Literal[
    "bad_request", "unsupported_version", "too_large", "ov_space_mismatch", "not_ready", "busy", "internal"
]
"""The error codes of wire protocol v1 (`{type: "error", code, message}`)."""

ERROR_CODES: tuple[str, ...] = get_args(ErrorCode)


class ProtocolError(Exception):
    """A message (or part of one) that the protocol rejects, or a request the node cannot serve.

    `code` is the wire error code, `message` a human-readable explanation that says what was
    wrong, the value received and the allowed range (it is sent back to the client verbatim).
    """

    def __init__(self, code: ErrorCode, message: str) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown protocol error code {code!r}; allowed: {', '.join(ERROR_CODES)}")
        super().__init__(f"{code}: {message}")
        self.code: ErrorCode = code
        self.message: str = message

    def __reduce__(self) -> tuple[type[ProtocolError], tuple[ErrorCode, str]]:
        # Keep the exception picklable (e.g. across multiprocessing) despite the 2-arg __init__.
        return (ProtocolError, (self.code, self.message))


class RemoteError(ProtocolError):
    """An `error` reply received from the mapper (raised by client-side `decode_as`).

    Distinguishes "the node refused my request" from "I could not parse the node's reply".
    `id` is the request id the error reply echoed.
    """

    def __init__(self, code: ErrorCode, message: str, id: int | str | None = None) -> None:
        super().__init__(code, message)
        self.id = id

    def __reduce__(self) -> tuple[Any, ...]:
        return (RemoteError, (self.code, self.message, self.id))
