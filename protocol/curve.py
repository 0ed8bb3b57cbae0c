"""CurveZMQ key files: the layout of a curve directory that the node and its clients share.

CurveZMQ is ZeroMQ's built-in authenticated encryption (Curve25519 key pairs; the node is the
CURVE server). Keys are stored in ``zmq.auth``'s own certificate format
(``zmq.auth.create_certificates``: a ZPL text file with ``public-key`` and, in ``.key_secret``,
``secret-key``), so any ZeroMQ client (pyzmq, czmq, zmqpp, JeroMQ...) can use them. Layout
(``govnesf keys DIR`` / ``govnesf keys DIR --client NAME``; docs/how-to/robot-network.md)::

    DIR/server.key               the node's public key: every client needs a copy
    DIR/server.key_secret        the node's secret key: stays on the node (mode 0600)
    DIR/allowed/NAME.key         public keys of the clients the node lets in
    DIR/clients/NAME.key         a client's public key (a copy goes into allowed/)
    DIR/clients/NAME.key_secret  a client's secret key: for that client only (mode 0600)

A client needs ``server.key`` and its own ``clients/NAME.key_secret``; nothing else.

Example::

    >>> import tempfile
    >>> root = tempfile.mkdtemp()
    >>> [p.name for p in create_server_keys(root)]
    ['server.key', 'server.key_secret', 'allowed']
    >>> [p.name for p in create_client_keys(root, "robot1")]
    ['robot1.key', 'robot1.key_secret', 'robot1.key']
    >>> keys = load_client_keys(root, "robot1")
    >>> len(keys.public), len(keys.server_public)
    (40, 40)
"""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SERVER_NAME = "server"
"""Certificate base name of the node: ``server.key`` / ``server.key_secret``."""
ALLOWED_DIR = "allowed"
"""Sub-directory of public client keys the node lets in."""
CLIENTS_DIR = "clients"
"""Sub-directory where client key pairs are made."""
CLIENT_NAME_PATTERN = r"[A-Za-z0-9_.-]{1,64}"
"""Allowed client names (they become file names)."""


class CurveKeyError(ValueError):
    """A key file is missing, unreadable or would be overwritten; the message says which and what to do."""


def validate_client_name(name: str) -> str:
    """Return ``name`` when it is a valid client name, else raise :class:`CurveKeyError`."""
    if not re.fullmatch(CLIENT_NAME_PATTERN, name) or set(name) == {"."}:
        raise CurveKeyError(
            f"client name {name!r} is invalid: use 1..64 characters from A-Z a-z 0-9 _ . - (not only dots)"
        )
    if name == SERVER_NAME:
        raise CurveKeyError(f"client name {name!r} is reserved for the node's own key")
    return name


def create_server_keys(directory: str | Path) -> list[Path]:
    """Make ``DIR/server.key``, ``DIR/server.key_secret`` (mode 0600) and an empty ``DIR/allowed/``.

    Refuses to overwrite an existing server key (every client holds a copy of its public half).
    Returns the paths made."""
    import zmq.auth

    root = Path(directory)
    public, secret = root / f"{SERVER_NAME}.key", root / f"{SERVER_NAME}.key_secret"
    if public.exists() or secret.exists():
        raise CurveKeyError(
            f"{root}: a server key already exists ({public.name}); clients hold a copy of it, so it is "
            "not replaced. Delete both server.key files by hand to make a new one (every client then "
            "needs the new server.key)"
        )
    root.mkdir(parents=True, exist_ok=True)
    (root / ALLOWED_DIR).mkdir(exist_ok=True)
    pub, sec = zmq.auth.create_certificates(str(root), SERVER_NAME)
    os.chmod(sec, 0o600)
    return [Path(pub), Path(sec), root / ALLOWED_DIR]


def create_client_keys(directory: str | Path, name: str) -> list[Path]:
    """Make ``DIR/clients/NAME.key`` + ``NAME.key_secret`` (mode 0600) and copy ``NAME.key`` into
    ``DIR/allowed/``. Refuses to overwrite a client key of that name. Returns the paths made."""
    import zmq.auth

    validate_client_name(name)
    root = Path(directory)
    clients = root / CLIENTS_DIR
    if (clients / f"{name}.key").exists() or (clients / f"{name}.key_secret").exists():
        raise CurveKeyError(f"{clients}: a key for client {name!r} already exists; pick another name")
    clients.mkdir(parents=True, exist_ok=True)
    allowed = root / ALLOWED_DIR
    allowed.mkdir(parents=True, exist_ok=True)
    pub, sec = zmq.auth.create_certificates(str(clients), name)
    os.chmod(sec, 0o600)
    copy = allowed / f"{name}.key"
    shutil.copyfile(pub, copy)
    return [Path(pub), Path(sec), copy]


def load_certificate(path: Path, what: str, *, need_secret: bool) -> tuple[bytes, bytes | None]:
    """``(public, secret)`` z85 keys of a certificate file (secret None for a public one)."""
    import zmq.auth

    if not path.is_file():
        raise CurveKeyError(
            f"{what}: {path} not found (make keys with `govnesf keys DIR`; docs/how-to/robot-network.md)")
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as exc:
        raise CurveKeyError(f"{what}: {path} is not a ZeroMQ certificate file: {exc}") from None
    if need_secret and not secret:
        raise CurveKeyError(f"{what}: {path} holds no secret key")
    return public, secret


def load_server_keys(curve_dir: str | Path) -> tuple[bytes, bytes]:
    """The node's ``(public, secret)`` keys from ``DIR/server.key_secret``."""
    public, secret = load_certificate(
        Path(curve_dir) / f"{SERVER_NAME}.key_secret", "node secret key", need_secret=True
    )
    assert secret is not None
    return public, secret


@dataclass(frozen=True)
class ClientCurveKeys:
    """What a client socket needs: its own key pair and the node's public key (z85 bytes)."""

    public: bytes
    secret: bytes
    server_public: bytes

    def apply(self, sock: Any) -> None:
        """Make ZeroMQ socket ``sock`` a CURVE client of the node (call before ``connect``)."""
        sock.curve_publickey = self.public
        sock.curve_secretkey = self.secret
        sock.curve_serverkey = self.server_public


def load_client_keys(curve_dir: str | Path, name: str) -> ClientCurveKeys:
    """The keys of client ``name``: ``DIR/server.key`` (the public one suffices) and
    ``DIR/clients/NAME.key_secret``. Raises :class:`CurveKeyError` naming a missing file."""
    validate_client_name(name)
    root = Path(curve_dir)
    server_public, _ = load_certificate(root / f"{SERVER_NAME}.key", "server public key", need_secret=False)
    public, secret = load_certificate(
        root / CLIENTS_DIR / f"{name}.key_secret", f"client {name!r} key", need_secret=True
    )
    assert secret is not None
    return ClientCurveKeys(public=public, secret=secret, server_public=server_public)
