"""Client library for the mapper node: send frames, ask queries, with timeouts and retries.

Reliability follows the ZeroMQ guide's "lazy pirate" pattern: every request waits for its
reply at most ``timeout_s``; on a timeout the socket is closed and re-created (dropping any
late reply of the dead socket) and the requests in flight are sent again, up to ``retries``
times, after which a :class:`TimeoutError` says which endpoint did not answer. A frame sent
twice this way is handled twice by the node (the second copy is usually just ``accepted``).

With CurveZMQ (a node served with ``--curve-dir``; docs/how-to/robot-network.md) pass
``curve=load_client_keys(DIR, NAME)`` (or ``--curve-dir DIR --client NAME`` on every CLI command,
:func:`add_curve_arguments`): every socket is then a CURVE client of the node. A client the node
does not allow gets no reply at all, so it sees a :class:`TimeoutError`.

:meth:`MapperClient.ping` asks for ``status`` once, with a short timeout and no retry, and raises
:class:`NodeUnreachableError` (a :class:`TimeoutError`) naming the endpoint when nothing answers:
the CLI commands ping first, so that a missing node is reported in seconds, and only then wait
the long timeout of a render or a query.

Frames go over one DEALER socket and may be pipelined (:meth:`MapperClient.send_frames`,
``window`` frames in flight). Replies are paired with requests by the echoed ``id`` (the client
gives every :class:`Frame` and request one); raw frame bytes without an id are paired in order,
which is exact because the node serves each socket from one thread and answers every message.

Example (needs a running node)::

    with MapperClient(ingest="tcp://127.0.0.1:5555", query="tcp://127.0.0.1:5556") as client:
        ack = client.send_frame(frame)             # -> Ack
        for result in client.send_frames(frames, window=8):
            print(result.index, result.reply)      # Ack or Error
        print(client.status().keyframes)
"""

from __future__ import annotations

import argparse
import copy
import itertools
import time
from collections import deque
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

import numpy as np
import zmq

from protocol.curve import ClientCurveKeys, CurveKeyError, load_client_keys
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import (
    MAX_MESSAGE_BYTES,
    Ack,
    Error,
    Frame,
    Load,
    Message,
    Ok,
    Points,
    QueryPoints,
    Render,
    RenderResult,
    RequestId,
    Save,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
    peek_id,
)

DEFAULT_INGEST = "tcp://127.0.0.1:5555"
DEFAULT_QUERY = "tcp://127.0.0.1:5556"

R = TypeVar("R", bound=Message)


class NodeUnreachableError(TimeoutError):
    """No node answered a ping (:meth:`MapperClient.ping`) at ``endpoint`` within ``timeout_s``."""

    def __init__(self, endpoint: str, timeout_s: float, curve: bool = False) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        hint = " and does it allow this client's CurveZMQ key" if curve else ""
        super().__init__(
            f"no node answers at {endpoint} ({timeout_s:.1f} s); is `govnesf serve` running{hint}?"
        )


@dataclass(frozen=True)
class FrameResult:
    """The node's answer to one frame of :meth:`MapperClient.send_frames`."""

    index: int
    """Position of the frame in the input iterable."""
    reply: Ack | Error
    """The ``ack`` (keyframe / accepted / rejected) or ``error`` reply."""
    latency_s: float
    """Seconds from (the last) sending of the frame to its reply."""


class _Channel:
    """One lazily created DEALER socket to one endpoint, re-created after a timeout."""

    def __init__(
        self, context: zmq.Context[zmq.Socket[bytes]], endpoint: str, curve: ClientCurveKeys | None = None
    ) -> None:
        self.context = context
        self.endpoint = endpoint
        self.curve = curve
        self._socket: zmq.Socket[bytes] | None = None

    @property
    def socket(self) -> zmq.Socket[bytes]:
        if self._socket is None:
            sock: zmq.Socket[bytes] = self.context.socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            if self.curve is not None:
                self.curve.apply(sock)
            sock.connect(self.endpoint)
            self._socket = sock
        return self._socket

    def reset(self) -> None:
        if self._socket is not None:
            self._socket.close(linger=0)
            self._socket = None

    def send(self, payload: bytes, timeout_s: float) -> None:
        # An empty delimiter first: the REQ-style envelope, which the node echoes back.
        sock = self.socket
        sock.setsockopt(zmq.SNDTIMEO, max(1, int(timeout_s * 1000)))
        try:
            sock.send_multipart([b"", payload], copy=False)
        except zmq.Again:  # the outgoing queue is full and nobody takes from it
            self.reset()
            raise TimeoutError(
                f"could not send to {self.endpoint} within {timeout_s:g} s (outgoing queue full): "
                "is the mapper node running there?"
            ) from None

    def exchange(
        self,
        payloads: Iterable[bytes],
        *,
        window: int,
        timeout_s: float,
        retries: int,
        rate_hz: float = 0.0,
    ) -> Generator[tuple[int, bytes, float], None, None]:
        """Send ``payloads`` with up to ``window`` in flight; yield ``(index, reply, latency_s)``
        as replies arrive. A reply is paired with the in-flight request carrying the same ``id``;
        without ids, with the oldest one (replies of a connection come back in order).
        Raises :class:`TimeoutError` after ``retries`` re-sends without any reply."""
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if retries < 0 or timeout_s <= 0:
            raise ValueError(f"need retries >= 0 and timeout_s > 0, got {retries}, {timeout_s}")
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        source = enumerate(payloads)
        exhausted = False
        inflight: deque[_InFlight] = deque()
        next_send = time.monotonic()
        deadline = 0.0
        failures = 0
        try:
            while True:
                now = time.monotonic()
                while not exhausted and len(inflight) < window and now >= next_send:
                    item = next(source, None)
                    if item is None:
                        exhausted = True
                        break
                    index, payload = item
                    if not inflight:
                        deadline = now + timeout_s
                    self.send(payload, timeout_s)
                    inflight.append(_InFlight(index, payload, now, peek_id(payload)))
                    if period:
                        next_send = max(next_send + period, now - period)
                    now = time.monotonic()
                if not inflight:
                    if exhausted:
                        return
                    time.sleep(max(0.0, next_send - time.monotonic()))
                    continue
                wait_s = deadline - now
                if period and not exhausted and len(inflight) < window:
                    wait_s = min(wait_s, next_send - now)
                if self.socket.poll(max(0, int(wait_s * 1000))):
                    parts = self.socket.recv_multipart()
                    entry = _pop_match(inflight, peek_id(parts[-1]))
                    received = time.monotonic()
                    deadline = received + timeout_s
                    failures = 0
                    yield entry.index, parts[-1], received - entry.sent_at
                elif time.monotonic() >= deadline:
                    failures += 1
                    if failures > retries:
                        raise TimeoutError(
                            f"no reply from {self.endpoint} within {timeout_s:g} s after {retries} "
                            f"retr{'y' if retries == 1 else 'ies'}: is the mapper node running there?"
                        )
                    self.reset()  # lazy pirate: a fresh socket, then send what is in flight again
                    resend_at = time.monotonic()
                    for entry in inflight:
                        self.send(entry.payload, timeout_s)
                        entry.sent_at = resend_at
                    deadline = resend_at + timeout_s
        finally:
            if inflight:
                # Abandoned (consumer stopped, error or timeout) with replies outstanding: drop the
                # socket so that late replies can never be paired with a later request.
                self.reset()


def add_curve_arguments(parser: argparse.ArgumentParser) -> None:
    """The connection options every CLI command shares for a node served with CurveZMQ:
    ``--curve-dir DIR --client NAME`` (read back with :func:`curve_from_args`)."""
    group = parser.add_argument_group(
        "CurveZMQ (a node served with --curve-dir; docs/how-to/robot-network.md)")
    group.add_argument(
        "--curve-dir", metavar="DIR", default=None,
        help="curve directory holding server.key and clients/NAME.key_secret (from `govnesf keys`)",
    )
    group.add_argument("--client", metavar="NAME", default=None, help="this client's key name in DIR")


def curve_from_args(args: argparse.Namespace) -> ClientCurveKeys | None:
    """The CURVE keys named by :func:`add_curve_arguments`' options (None when not given).
    Raises ``ProtocolError`` (``bad_request``) with a clear message when only one is given or a
    key file is missing: CLI commands report it like any invalid argument (exit code 2)."""
    curve_dir, name = getattr(args, "curve_dir", None), getattr(args, "client", None)
    if curve_dir is None and name is None:
        return None
    if curve_dir is None or name is None:
        raise ProtocolError("bad_request", "--curve-dir DIR and --client NAME go together")
    try:
        return load_client_keys(curve_dir, name)
    except CurveKeyError as exc:
        raise ProtocolError("bad_request", f"CurveZMQ keys: {exc}") from None


@dataclass
class _InFlight:
    index: int
    payload: bytes
    sent_at: float
    id: RequestId


def _pop_match(inflight: deque[_InFlight], reply_id: RequestId) -> _InFlight:
    """Remove and return the oldest in-flight request with ``reply_id`` (else the oldest one)."""
    if reply_id is not None:
        for entry in inflight:
            if entry.id == reply_id:
                inflight.remove(entry)
                return entry
    return inflight.popleft()


class MapperClient:
    """Talks to one mapper node: frames to ``ingest``, requests to ``query``. Not thread-safe
    (one client per thread, like the ZeroMQ sockets it owns)."""

    def __init__(
        self,
        ingest: str = DEFAULT_INGEST,
        query: str = DEFAULT_QUERY,
        *,
        timeout_s: float = 5.0,
        retries: int = 2,
        max_reply_bytes: int = MAX_MESSAGE_BYTES,
        context: zmq.Context[zmq.Socket[bytes]] | None = None,
        curve: ClientCurveKeys | None = None,
    ) -> None:
        """
        Args:
            ingest, query: the node's endpoints.
            timeout_s: how long to wait for each reply before retrying (seconds, > 0).
            retries: how many times to re-create the socket and resend before giving up (>= 0).
            max_reply_bytes: replies larger than this are refused (``too_large``).
            context: a ZeroMQ context to share; by default the client makes (and terminates) its own.
            curve: CurveZMQ keys (:func:`protocol.curve.load_client_keys`) for a node served with
                ``curve_dir``; None = plain ZeroMQ.
        """
        if timeout_s <= 0 or retries < 0:
            raise ValueError(f"timeout_s must be > 0 and retries >= 0, got {timeout_s} and {retries}")
        self.timeout_s = timeout_s
        self.retries = retries
        self.max_reply_bytes = max_reply_bytes
        self._own_context = context is None
        self._context: zmq.Context[zmq.Socket[bytes]] = context if context is not None else zmq.Context()
        self._ingest = _Channel(self._context, ingest, curve)
        self._query = _Channel(self._context, query, curve)
        self._curve = curve is not None
        self._ids = itertools.count(1)

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the sockets (and the context if the client made it). Idempotent."""
        self._ingest.reset()
        self._query.reset()
        if self._own_context and not self._context.closed:
            self._context.term()

    def __enter__(self) -> MapperClient:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- frames -------------------------------------------------------------------------------

    def send_frame(self, frame: Frame | bytes, *, timeout_s: float | None = None) -> Ack:
        """Send one frame (a :class:`Frame` or its wire bytes) and wait for its ``ack``.

        Raises:
            RemoteError: the node answered with an ``error`` (code and message inside).
            TimeoutError: no reply after the retries.
        """
        result = next(iter(self.send_frames([frame], window=1, timeout_s=timeout_s)))
        if isinstance(result.reply, Error):
            raise RemoteError(result.reply.code, result.reply.message, result.reply.id)
        return result.reply

    def send_frames(
        self,
        frames: Iterable[Frame | bytes],
        *,
        window: int = 8,
        rate_hz: float = 0.0,
        timeout_s: float | None = None,
    ) -> Generator[FrameResult, None, None]:
        """Pipelined ingest: keep up to ``window`` frames in flight, yield one result per frame as
        the replies arrive (in input order unless a reply had to be re-requested; ``index`` says
        which frame). ``rate_hz`` > 0 sends at most that many frames per second.

        :class:`Frame` objects without an ``id`` are sent with one (a copy; the caller's object is
        unchanged); raw bytes are sent unchanged. Error replies are yielded, not raised.

        Raises:
            TimeoutError: the node stopped answering (after the retries).
            ProtocolError: a reply that is not a valid ``ack``/``error``, or that echoes another id.
        """
        expected_ids: dict[int, RequestId] = {}

        def payloads() -> Iterator[bytes]:
            for index, frame in enumerate(frames):
                if isinstance(frame, Frame):
                    if frame.id is None:
                        frame = copy.copy(frame)
                        frame.id = next(self._ids)
                    expected_ids[index] = frame.id
                    yield encode(frame)
                elif isinstance(frame, bytes | bytearray | memoryview):
                    data = bytes(frame)
                    expected_ids[index] = peek_id(data)
                    yield data
                else:
                    raise TypeError(f"frames must be Frame or bytes, got {type(frame).__name__}")

        for index, data, latency_s in self._ingest.exchange(
            payloads(),
            window=window,
            timeout_s=self.timeout_s if timeout_s is None else timeout_s,
            retries=self.retries,
            rate_hz=rate_hz,
        ):
            reply = decode(data, max_bytes=self.max_reply_bytes, direction="reply")
            if not isinstance(reply, Ack | Error):
                raise ProtocolError(
                    "bad_request", f"expected an ack or error reply to a frame, got {reply.TYPE!r}"
                )
            sent_id = expected_ids.pop(index, None)
            if sent_id is not None and reply.id is not None and reply.id != sent_id:
                raise ProtocolError(
                    "bad_request",
                    f"reply echoes id {reply.id!r} but frame {index} was sent with id {sent_id!r}",
                )
            yield FrameResult(index=index, reply=reply, latency_s=latency_s)

    # -- queries ------------------------------------------------------------------------------

    @property
    def query_endpoint(self) -> str:
        """The node's query endpoint this client talks to."""
        return self._query.endpoint

    def ping(self, timeout_s: float = 2.0) -> Status:
        """One ``status`` request, waiting at most ``timeout_s`` and never retried: is a node there?

        Raises:
            NodeUnreachableError: no reply within ``timeout_s`` (no node, a node behind other keys,
                or a node busy for longer than that on another client's ``save`` / ``load``).
            RemoteError: the node answered with an ``error``.
        """
        try:
            return self._call(StatusRequest(), Status, timeout_s, retries=0)
        except TimeoutError:
            raise NodeUnreachableError(self._query.endpoint, timeout_s, self._curve) from None

    def request(self, msg: Message, *, timeout_s: float | None = None, retries: int | None = None) -> Message:
        """Send one request to the query endpoint and return the reply message as received
        (an :class:`Error` reply is returned, not raised). Requests without an ``id`` get one.
        ``timeout_s`` / ``retries`` override the client's for this request."""
        if getattr(msg, "id", "absent") is None:
            msg = copy.copy(msg)
            msg.id = next(self._ids)  # type: ignore[attr-defined]
        sent_id = getattr(msg, "id", None)
        results = self._query.exchange(
            [encode(msg)],
            window=1,
            timeout_s=self.timeout_s if timeout_s is None else timeout_s,
            retries=self.retries if retries is None else retries,
        )
        try:
            _, data, _ = next(results)
        finally:
            results.close()
        reply = decode(data, max_bytes=self.max_reply_bytes, direction="reply")
        reply_id = getattr(reply, "id", None)
        if sent_id is not None and reply_id is not None and reply_id != sent_id:
            raise ProtocolError("bad_request", f"reply echoes id {reply_id!r}, request had id {sent_id!r}")
        return reply

    def _call(
        self, msg: Message, expected: type[R], timeout_s: float | None = None, retries: int | None = None
    ) -> R:
        reply = self.request(msg, timeout_s=timeout_s, retries=retries)
        if isinstance(reply, Error):
            raise RemoteError(reply.code, reply.message, reply.id)
        if not isinstance(reply, expected):
            raise ProtocolError(
                "bad_request", f"expected a {expected.TYPE!r} reply to {msg.TYPE!r}, got {reply.TYPE!r}"
            )
        return reply

    def status(self, *, timeout_s: float | None = None) -> Status:
        """The node's status (counters, map version, memory...)."""
        return self._call(StatusRequest(), Status, timeout_s)

    def save(self, name: str, *, timeout_s: float | None = None) -> Ok:
        """Save the map as ``name`` in the node's map directory. Raises RemoteError on failure."""
        return self._call(Save(name=name), Ok, timeout_s)

    def load(self, name: str, *, timeout_s: float | None = None) -> Ok:
        """Replace the node's map with the saved map ``name``. Raises RemoteError on failure."""
        return self._call(Load(name=name), Ok, timeout_s)

    def query_points(
        self,
        texts: list[str],
        *,
        negatives: list[str] | None = None,
        min_score: float | None = None,
        max_points: int | None = None,
        objects: bool = True,
        settle_timeout_s: float | None = None,
        region: tuple[np.ndarray, np.ndarray] | None = None,  # ((3,), (3,)) world box min, max (m)
        timeout_s: float | None = None,
    ) -> Points:
        """"Find the chair": map points (and object candidates) matching ``texts``. With
        ``settle_timeout_s`` the node first waits (up to that long) for its background work on the
        frames acked so far; the reply's ``settled`` says whether none was pending. Give the call a
        ``timeout_s`` longer than that wait. ``region``: only map points inside that axis-aligned box."""
        low = None if region is None else np.asarray(region[0], float)
        high = None if region is None else np.asarray(region[1], float)
        msg = QueryPoints(
            texts=texts, negatives=negatives, min_score=min_score, max_points=max_points, objects=objects,
            settle_timeout_s=settle_timeout_s, region_min=low, region_max=high,
        )
        return self._call(msg, Points, timeout_s)

    def segment_points(
        self,
        xyz: np.ndarray,  # (N, 3) float32 world points, metres
        texts: list[str],
        *,
        method: str = "govnesf",
        use_depth: bool = False,
        settle_timeout_s: float | None = None,
        timeout_s: float | None = None,
    ) -> Segmentation:
        """Label world points with one of ``texts`` (3D semantic segmentation); ``settle_timeout_s``
        as for :meth:`query_points`. The reply's ``fallback`` marks points the averaging answered for
        the learned method (its geometry still pending)."""
        msg = SegmentPoints(xyz=xyz, texts=texts, method=method, use_depth=use_depth,  # type: ignore[arg-type]
                            settle_timeout_s=settle_timeout_s)
        return self._call(msg, Segmentation, timeout_s)

    def render(
        self,
        width: int,
        height: int,
        K: np.ndarray,  # (4,) [fx, fy, cx, cy] pixels
        world_from_cam: np.ndarray,  # (4, 4) camera-to-world
        outputs: list[str],
        texts: list[str] | None = None,
        *,
        settle_timeout_s: float | None = None,
        timeout_s: float | None = None,
    ) -> RenderResult:
        """Render colour / depth / label / score from any pose; ``settle_timeout_s`` as for
        :meth:`query_points`."""
        msg = Render(
            width=width, height=height, K=K, world_from_cam=world_from_cam, outputs=outputs, texts=texts,
            settle_timeout_s=settle_timeout_s,
        )
        return self._call(msg, RenderResult, timeout_s)
