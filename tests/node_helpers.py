"""Shared helpers of the tests that run a :class:`MapperNode` in-process (no subprocess), or a
scripted stand-in for its query endpoint."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import zmq

from clients.harness import DEMO_OV_DIM, DEMO_OV_SPACE, free_endpoints
from mapper.node.config import NodeConfig, config_from_dict
from mapper.node.service import MapperNode
from protocol.messages import Message, Points, RenderResult, Status, StatusRequest, decode, encode

RequestT = TypeVar("RequestT", bound=Message)


def node_config(tmp_path: Path, **settings: Any) -> NodeConfig:
    """A node's config on free loopback ports, no events endpoint, its maps under
    ``tmp_path/maps`` and a fast poll; ``settings`` (TOML-shaped) add to or override these."""
    if "ingest_endpoint" in settings and "query_endpoint" in settings:
        ingest, query = settings["ingest_endpoint"], settings["query_endpoint"]
    else:
        ingest, query = free_endpoints(2)
    return config_from_dict(
        {
            "ingest_endpoint": ingest,
            "query_endpoint": query,
            "events_endpoint": "",
            "map_dir": str(tmp_path / "maps"),
            "poll_interval_s": 0.02,
            **settings,
        }
    )


def in_process_node(tmp_path: Path, **settings: Any) -> MapperNode:
    """A (not started) node with :func:`node_config`."""
    return MapperNode(node_config(tmp_path, **settings))


class ScriptedQueryEndpoint(Generic[RequestT]):
    """A query endpoint on a free TCP port that answers every request (each must be a
    ``request_type``) with ``reply``, its ``id`` set to the request's, and records the requests;
    a ``status`` request (the CLI's ping) gets an empty map's status and is counted in ``pings``."""

    def __init__(self, request_type: type[RequestT], reply: Points | RenderResult) -> None:
        (self.endpoint,) = free_endpoints(1)
        self.request_type = request_type
        self.reply = reply
        self.requests: list[RequestT] = []
        self.pings = 0
        self._ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self._sock = self._ctx.socket(zmq.ROUTER)
        self._sock.bind(self.endpoint)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(20):
                continue
            parts = self._sock.recv_multipart()
            msg = decode(parts[-1], direction="request")
            if isinstance(msg, StatusRequest):
                self.pings += 1
                status = Status(
                    map_version=0, keyframes=0, frames_received=0, frames_rejected=0, ov_space=None,
                    memory_bytes=0, uptime_s=0.0, id=msg.id,
                )
                self._sock.send_multipart([*parts[:-1], encode(status)])
                continue
            assert isinstance(msg, self.request_type)
            self.requests.append(msg)
            self.reply.id = msg.id
            self._sock.send_multipart([*parts[:-1], encode(self.reply)])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sock.close(linger=0)
        self._ctx.term()


class DemoOneHotEncoder:
    """A text encoder for the synthetic frames' feature space (``clients.harness.DEMO_OV_SPACE``):
    ``sky``, ``dark``, ``light`` are its three channels; other prompts land on the spare ones."""

    space, dim = DEMO_OV_SPACE, DEMO_OV_DIM

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        rows = {"sky": 0, "dark": 1, "light": 2}
        return np.stack([np.eye(DEMO_OV_DIM, dtype=np.float32)[rows.get(t, 3 + len(t) % 5)] for t in texts])
