"""CurveZMQ for the node: key files, the ZAP authenticator, and the start-up exposure check.

CurveZMQ is ZeroMQ's built-in authenticated encryption (Curve25519 keys, per-connection session
keys). The node is the CURVE *server* on its ingest, query and events sockets; a ZAP
authenticator (:class:`zmq.auth.thread.ThreadAuthenticator`) lets through only clients whose
public key is a certificate file in ``CURVE_DIR/allowed/``. A client without CURVE, or with a
key that is not allowed, never completes the handshake: it gets no reply at all (it times out).

Key files are ``zmq.auth``'s own certificate format; their layout in a curve directory is
shared with the clients and lives in :mod:`protocol.curve` (``govnesf keys DIR``,
docs/how-to/robot-network.md).

The node re-reads ``allowed/`` while running (:meth:`CurveServer.reload_if_changed`): a key
added there is let in, a key removed is refused on its next connection.

This module is torch-free (node core).
"""

from __future__ import annotations

import ipaddress
import logging
from pathlib import Path

import zmq
from zmq.auth.thread import ThreadAuthenticator

from protocol.curve import ALLOWED_DIR, CurveKeyError, load_server_keys

log = logging.getLogger("mapper.node.security")

_LOOPBACK_HOSTS = {"localhost", "127.0.0.1", "::1", "[::1]"}


class CurveServer:
    """The node's CURVE server keys and its ZAP authenticator on one ZeroMQ context."""

    def __init__(self, context: zmq.Context[zmq.Socket[bytes]], curve_dir: str | Path) -> None:
        root = Path(curve_dir)
        self.curve_dir = root
        self.allowed_dir = root / ALLOWED_DIR
        self.public, self.secret = load_server_keys(root)
        if not self.allowed_dir.is_dir():
            raise CurveKeyError(
                f"curve_dir {str(root)!r} has no {ALLOWED_DIR}/ directory (make it: `govnesf keys {root}`)"
            )
        self._context = context
        self._auth: ThreadAuthenticator | None = None
        self._signature: tuple[tuple[str, int, int], ...] = ()
        self.allowed_keys = 0

    def start(self) -> None:
        """Start the ZAP authenticator thread and load ``allowed/``."""
        auth = ThreadAuthenticator(self._context, log=logging.getLogger("mapper.node.zap"))
        auth.start()
        self._auth = auth
        self._configure(auth)

    def _listing(self) -> tuple[tuple[str, int, int], ...]:
        try:
            entries = sorted(self.allowed_dir.iterdir())
        except OSError:
            return ()
        out = []
        for p in entries:
            try:
                st = p.stat()
            except OSError:
                continue
            out.append((p.name, st.st_mtime_ns, st.st_size))
        return tuple(out)

    def _configure(self, auth: ThreadAuthenticator) -> None:
        import zmq.auth

        self._signature = self._listing()
        keys = zmq.auth.load_certificates(str(self.allowed_dir))
        self.allowed_keys = len(keys)
        auth.configure_curve(domain="*", location=str(self.allowed_dir))
        log.info("CurveZMQ: %d allowed client key(s) in %s", self.allowed_keys, self.allowed_dir)

    def reload_if_changed(self) -> bool:
        """Re-read ``allowed/`` when a file was added, removed or changed; returns True if reloaded.
        Connections already authenticated stay up; the new list applies to new handshakes."""
        if self._auth is None or self._listing() == self._signature:
            return False
        self._configure(self._auth)
        return True

    def apply(self, sock: zmq.Socket[bytes]) -> None:
        """Make ``sock`` a CURVE server (call before ``bind``)."""
        sock.curve_secretkey = self.secret
        sock.curve_publickey = self.public
        sock.curve_server = True

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None


# -- exposure ---------------------------------------------------------------------------------


def is_loopback(endpoint: str) -> bool:
    """True for endpoints only this machine can reach: ``ipc://``, ``inproc://`` and tcp on
    127.0.0.0/8, ``localhost`` or ``::1``. ``tcp://*``, ``0.0.0.0``, LAN addresses and interface
    names are not loopback."""
    scheme, sep, rest = endpoint.partition("://")
    if scheme in ("ipc", "inproc"):
        return True
    if scheme != "tcp" or not sep:
        return False
    host = rest.rpartition(":")[0]
    if host in _LOOPBACK_HOSTS:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def exposure_problem(endpoints: list[str], curve_dir: str | None, insecure: bool) -> str | None:
    """Why the node must not start with these binds (None when it may): a non-loopback endpoint
    needs CURVE (``curve_dir``) or the explicit ``insecure`` choice."""
    remote = [e for e in endpoints if not is_loopback(e)]
    if not remote or curve_dir or insecure:
        return None
    return (
        f"refusing to bind {', '.join(remote)} without authentication: anyone who can reach that "
        "address could stream frames, query, save and load maps. Serve with CurveZMQ "
        "(`govnesf keys DIR`, then `govnesf serve --curve-dir DIR`; docs/how-to/robot-network.md), bind "
        "loopback only, or pass --insecure (insecure = true) to serve unauthenticated anyway"
    )


def security_mode(endpoints: list[str], curve_dir: str | None) -> str:
    """``"curve"``, ``"loopback"`` (no CURVE, every bind local) or ``"insecure"`` (no CURVE, some
    bind reachable from the network)."""
    if curve_dir:
        return "curve"
    return "loopback" if all(is_loopback(e) for e in endpoints) else "insecure"
