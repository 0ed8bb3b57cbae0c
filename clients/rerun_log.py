"""Logging for the Rerun viewer: to an ``.rrd`` file (``--rerun FILE.rrd`` of ``govnesf
query/render/replay`` and the demo) and/or live to a running viewer (``--rerun-connect ADDR``).

One place for all Rerun logging. ``rerun`` (the PyPI package ``rerun-sdk``, pinned in
pyproject.toml) is imported lazily, only when a recording is opened or a path is checked, so no
other command pays for it; a missing package is a :class:`RerunLogError` naming the pin.

Usage::

    path = check_rrd_path("out/chair.rrd")      # before any work: bad path -> RerunLogError
    ...
    with RerunLog(path) as rlog:                 # one RecordingStream (application id "govnesf")
        rlog.log_query(points, ["chair"])        # closed (flushed, footer written) on exit
    # view it: rerun out/chair.rrd

    url = check_connect_addr("127.0.0.1:9876")  # a viewer started with `rerun` listens there
    with RerunLog(connect=url) as rlog:          # live; RerunLog(path, connect=url) does both
        rlog.log_query(points, ["chair"])

Entity layout (world +z up, metres; see docs/how-to/rerun.md):

- ``world``: view coordinates right-handed, +z up (docs/concepts/conventions.md).
- ``world/cameras/<camera>``: ``Transform3D`` = ``world_from_cam`` (camera-to-world);
  ``.../image``: ``Pinhole`` with ``K`` and the OpenCV optical frame (RDF: x right, y down,
  z forward); ``.../image/rgb``, ``.../image/depth`` (z-depth in metres, 0 = none),
  ``.../image/label`` (``SegmentationImage``: label + 1, 0 = nothing rendered).
- ``world/query`` (or another entity per query): ``points`` (coloured by score, viridis),
  ``objects`` (AABBs, one label per object: text, score, points), ``centroids``.
- ``world/map``: map points coloured by their label.
- ``world/render``: a rendered view, as a camera.

Timelines: ``frame`` (the frame's ``seq``), ``stamp`` (its ``stamp_ns``) and ``map_version``
(query results), besides Rerun's own ``log_time``.
"""

from __future__ import annotations

import os
import re
import socket
import uuid
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from clients.colors import LABEL_COLORS, score_colours
from protocol.messages import Frame, ObjectCandidate, Points, RenderResult

if TYPE_CHECKING:  # for the annotations only; never imported at run time here
    import rerun

__all__ = [
    "APPLICATION_ID",
    "RERUN_PIN",
    "RerunLog",
    "RerunLogError",
    "CONNECT_HELP",
    "check_connect_addr",
    "check_rerun_outputs",
    "check_rrd_path",
    "import_rerun",
]

RERUN_PIN = "rerun-sdk==0.41.0"
"""The pinned package (pyproject.toml, constraints.txt)."""

APPLICATION_ID = "govnesf"
"""The Rerun application id of every recording written here."""

DEFAULT_VIEWER_PORT = 9876
"""Port of a viewer started with plain ``rerun`` (Rerun's default)."""

CONNECT_CHECK_TIMEOUT_S = 2.0
"""How long :func:`check_connect_addr` waits for the viewer's port to accept a TCP connection."""

FLUSH_TIMEOUT_S = 10.0
"""How long closing a live (``connect``) log waits for the viewer to take the data."""

NOTHING_COLOUR = (0, 0, 0)
"""Colour of label -1 (class id 0): nothing rendered / unlabelled."""


class RerunLogError(Exception):
    """A ``--rerun`` output cannot be written (bad path, package missing, logging disabled)."""


def import_rerun() -> ModuleType:
    """The ``rerun`` module; :class:`RerunLogError` naming the pin when it is not installed."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise RerunLogError(
            f"--rerun needs the Python package {RERUN_PIN} (the Rerun SDK), which is not importable "
            f"({exc}); install the extra: pip install 'govnesf[rerun]' (in a checkout: make setup)"
        ) from exc
    return rr


def _rerun_disabled_by_env() -> bool:
    """Rerun's own switch: ``RERUN=0/false/off/no`` turns every recording off."""
    return os.environ.get("RERUN", "").strip().lower() in {"0", "false", "off", "no"}


_URL = re.compile(r"(rerun|rerun\+http|rerun\+https)://([^/:\s]+|\[[0-9a-fA-F:]+\]):(\d{1,5})/proxy")
_HOST_PORT = re.compile(r"([^/:\s]+|\[[0-9a-fA-F:]+\]):(\d{1,5})")


def check_connect_addr(addr: str, *, probe: bool = True) -> str:
    """Check, before any work, the ``--rerun-connect`` address of a running Rerun viewer (or
    ``rerun --serve-grpc`` proxy); returns its gRPC URL.

    ``addr`` is ``PORT`` (on 127.0.0.1), ``HOST:PORT``, or a URL ``rerun+http://HOST:PORT/proxy``
    (also ``rerun://`` and ``rerun+https://``, as Rerun's ``connect_grpc`` takes them). With
    ``probe``, the port must accept a TCP connection within :data:`CONNECT_CHECK_TIMEOUT_S`
    (otherwise Rerun would buffer and fail only at the end). Raises :class:`RerunLogError` with the
    reason: the package is missing, ``RERUN=off``, a malformed address, or nothing listens there.
    """
    import_rerun()
    if _rerun_disabled_by_env():
        raise RerunLogError(
            f"--rerun-connect {addr}: the environment variable RERUN={os.environ.get('RERUN')} turns "
            "Rerun logging off; unset it to stream to a viewer"
        )
    text = addr.strip()
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    url_match = _URL.fullmatch(text)
    host_match = None if url_match else _HOST_PORT.fullmatch(text)
    if url_match:
        url, host, port = text, url_match.group(2), int(url_match.group(3))
    elif host_match:
        host, port = host_match.group(1), int(host_match.group(2))
        url = f"rerun+http://{host}:{port}/proxy"
    else:
        raise RerunLogError(
            f"--rerun-connect {addr!r}: expected PORT, HOST:PORT or rerun+http://HOST:PORT/proxy "
            f"(a viewer started with `rerun` listens on 127.0.0.1:{DEFAULT_VIEWER_PORT})"
        )
    if not 1 <= port <= 65535:
        raise RerunLogError(f"--rerun-connect {addr!r}: port {port} is not in 1..65535")
    if probe:
        try:
            with socket.create_connection((host.strip("[]"), port), timeout=CONNECT_CHECK_TIMEOUT_S):
                pass
        except OSError as exc:
            raise RerunLogError(
                f"--rerun-connect {addr}: no Rerun viewer answers at {host}:{port} "
                f"({exc.strerror or exc}); start one first (`rerun --port {port}`, or "
                f"`rerun --serve-grpc --port {port}` without a display)"
            ) from None
    return url


CONNECT_HELP = (
    "also stream it live to a running Rerun viewer: PORT, HOST:PORT or rerun+http://HOST:PORT/proxy "
    f"(a viewer started with `rerun` listens on 127.0.0.1:{DEFAULT_VIEWER_PORT}); with --rerun, both"
)
"""``--help`` text of ``--rerun-connect`` (the same in every command)."""


def check_rerun_outputs(path: str | Path | None, connect: str | None) -> None:
    """The checks of ``--rerun PATH`` (:func:`check_rrd_path`) and ``--rerun-connect ADDR``
    (:func:`check_connect_addr`) for the ones given; :class:`RerunLogError` on the first problem."""
    if path is not None:
        check_rrd_path(path)
    if connect is not None:
        check_connect_addr(connect)


def check_rrd_path(path: str | Path) -> Path:
    """Check, before any work, that ``path`` can become an ``.rrd`` file; returns it as a Path.

    Changes nothing on disk. Raises :class:`RerunLogError` with the reason: the package is
    missing, ``RERUN=off`` is set, the name does not end in ``.rrd``, the path is a directory,
    its directory is missing, not a directory or not writable, or an existing file is not
    writable. Missing directories are not created (a typo should not grow a tree).
    """
    import_rerun()
    if _rerun_disabled_by_env():
        raise RerunLogError(
            f"--rerun {path}: the environment variable RERUN={os.environ.get('RERUN')} turns Rerun "
            "logging off; unset it to write the file"
        )
    p = Path(path).expanduser()
    if p.suffix != ".rrd":
        raise RerunLogError(f"--rerun {path}: the file name must end in .rrd (e.g. out/view.rrd)")
    if p.is_dir():
        raise RerunLogError(f"--rerun {path}: is a directory; give a file name such as {p / 'log.rrd'}")
    parent = p.parent
    if not parent.exists():
        raise RerunLogError(f"--rerun {path}: directory {parent} does not exist (create it first)")
    if not parent.is_dir():
        raise RerunLogError(f"--rerun {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise RerunLogError(f"--rerun {path}: directory {parent} is not writable")
    if p.exists() and not os.access(p, os.W_OK):
        raise RerunLogError(f"--rerun {path}: the existing file is not writable")
    return p


# ---------------------------------------------------------------------------------------------
# argument checks (Rerun itself only warns on malformed data; a wrong shape here is a bug)


def _array(name: str, value: Any, shape: tuple[int | None, ...], dtype: Any = None) -> np.ndarray:
    arr = np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape, strict=True)):
        dims = ", ".join("N" if s is None else str(s) for s in shape)
        want = f"({dims},)" if len(shape) == 1 else f"({dims})"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


def _annotation(texts: Sequence[str]) -> list[tuple[int, str, tuple[int, int, int]]]:
    """Class id 0 = nothing, class id i + 1 = texts[i] in the render CLI's label colours."""
    out = [(0, "nothing", NOTHING_COLOUR)]
    for i, text in enumerate(texts):
        r, g, b = (int(c) for c in LABEL_COLORS[i % len(LABEL_COLORS)])
        out.append((i + 1, text, (r, g, b)))
    return out


def label_colours(label: np.ndarray) -> np.ndarray:  # (N,) int -> (N, 3) uint8
    """The render CLI's label colours (tab10, cycled) per label index; -1 is black."""
    label = np.asarray(label, np.int64)
    out = LABEL_COLORS[np.maximum(label, 0) % len(LABEL_COLORS)].copy()
    out[label < 0] = NOTHING_COLOUR
    return out


class RerunLog:
    """One Rerun ``RecordingStream`` (application id ``"govnesf"``) saved to the ``.rrd`` file
    ``path`` and/or streamed live to the viewer at ``connect`` (a gRPC URL or address, see
    :func:`check_connect_addr`). A context manager; :meth:`close` flushes and writes the file's
    footer, so the file is complete (and the viewer has everything) when it returns. ``path`` is
    checked with :func:`check_rrd_path` and ``connect`` with :func:`check_connect_addr` first."""

    def __init__(
        self, path: str | Path | None = None, *, connect: str | None = None, recording_name: str | None = None
    ) -> None:
        if path is None and connect is None:
            raise RerunLogError("RerunLog needs a file path, a viewer address (connect=...) or both")
        self.path = check_rrd_path(path) if path is not None else None
        self.url = check_connect_addr(connect) if connect is not None else None
        """gRPC URL of the live viewer, or None."""
        self._rr = import_rerun()
        rr = self._rr
        self.rec: rerun.RecordingStream = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        if not self.rec.is_enabled():
            raise RerunLogError(
                f"--rerun {path or connect}: Rerun logging is disabled in this environment (RERUN)"
            )
        if self.path is not None and self.url is not None:
            self.rec.set_sinks(rr.FileSink(self.path), rr.GrpcSink(self.url))
        elif self.path is not None:
            self.rec.save(self.path)
        else:
            self.rec.connect_grpc(self.url)
        if recording_name:
            self.rec.send_recording_name(recording_name)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.closed = False
        self.frames_logged = 0
        """Frames logged by :meth:`log_frame`."""

    # -- lifecycle ------------------------------------------------------------------------------

    def close(self) -> None:
        """Flush everything and close the file and the viewer connection (idempotent).

        Raises:
            RerunLogError: the live viewer did not take the data within :data:`FLUSH_TIMEOUT_S`
                (the file, if any, is still complete).
        """
        if self.closed:
            return
        self.closed = True
        try:
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S if self.url is not None else 1e38)
        except RuntimeError as exc:  # the gRPC sink could not deliver
            self.rec.disconnect()
            raise RerunLogError(
                f"--rerun-connect {self.url}: the viewer did not take the data: {exc}"
            ) from None
        self.rec.disconnect()  # finalises the file sink: footer written, file closed

    def __enter__(self) -> RerunLog:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- time -------------------------------------------------------------------------------------

    def set_frame(self, seq: int, stamp_ns: int | None = None) -> None:
        """Put what follows on the ``frame`` timeline at ``seq`` (and ``stamp`` at ``stamp_ns``)."""
        self.rec.set_time("frame", sequence=int(seq))
        if stamp_ns is not None:
            self.rec.set_time("stamp", timestamp=np.datetime64(int(stamp_ns), "ns"))

    # -- cameras and images -------------------------------------------------------------------

    def log_camera(
        self,
        entity: str,
        K: np.ndarray,  # (4,) [fx, fy, cx, cy] pixels, for the image as sent
        world_from_cam: np.ndarray,  # (4, 4) camera-to-world, metres
        width: int,
        height: int,
        *,
        rgb: np.ndarray | None = None,  # (H, W, 3) uint8
        depth_m: np.ndarray | None = None,  # (H, W) float32 z-depth, metres, 0 = none
        label: np.ndarray | None = None,  # (H, W) int, index into texts, -1 = nothing
        texts: Sequence[str] | None = None,  # label names (class ids label + 1)
    ) -> None:
        """A posed pinhole camera at ``entity`` with its images under ``entity/image``.

        The pose is ``world_from_cam`` (parent-from-child, as Rerun's ``Transform3D`` expects);
        the pinhole uses ``K`` unchanged and the OpenCV optical frame (RDF). Rerun and the
        project share the pixel convention: the image spans ``[0, W] x [0, H]``.
        """
        rr = self._rr
        fx, fy, cx, cy = (float(v) for v in _array("K", K, (4,), np.float64))
        pose = _array("world_from_cam", world_from_cam, (4, 4), np.float64)
        if not np.all(np.isfinite(pose)) or not np.all(np.isfinite([fx, fy, cx, cy])):
            raise ValueError("K and world_from_cam must be finite")
        if width < 1 or height < 1:
            raise ValueError(f"image size {width}x{height} must be positive")
        self.rec.log(entity, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        self.rec.log(
            f"{entity}/image",
            rr.Pinhole(
                image_from_camera=[[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
                resolution=[width, height],
                camera_xyz=rr.ViewCoordinates.RDF,
            ),
        )
        if rgb is not None:
            self.rec.log(f"{entity}/image/rgb", rr.Image(_array("rgb", rgb, (height, width, 3), np.uint8)))
        if depth_m is not None:
            depth = _array("depth_m", depth_m, (height, width), np.float32)
            self.rec.log(f"{entity}/image/depth", rr.DepthImage(depth, meter=1.0))
        if label is not None:
            lab = _array("label", label, (height, width), np.int64)
            if texts is not None:
                self.rec.log(f"{entity}/image/label", rr.AnnotationContext(_annotation(texts)), static=True)
            ids = (np.maximum(lab, -1) + 1).astype(np.uint16)
            self.rec.log(f"{entity}/image/label", rr.SegmentationImage(ids))

    def log_frame(self, frame: Frame, *, root: str = "world/cameras") -> None:
        """A streamed frame: camera ``root/<frame.camera>`` at ``frame`` = ``seq``, ``stamp`` =
        ``stamp_ns``, with its rgb and depth (when present)."""
        self.set_frame(frame.seq, frame.stamp_ns)
        camera = self._rr.escape_entity_path_part(frame.camera)
        self.log_camera(
            f"{root}/{camera}", frame.K, frame.world_from_cam, frame.width, frame.height,
            rgb=frame.rgb, depth_m=frame.depth_m,
        )  # fmt: skip
        self.frames_logged += 1

    def log_render(
        self,
        result: RenderResult,
        K: np.ndarray,  # (4,) [fx, fy, cx, cy] of the request
        world_from_cam: np.ndarray,  # (4, 4) of the request
        texts: Sequence[str] | None = None,  # the request's label set
        *,
        entity: str = "world/render",
    ) -> None:
        """A rendered view: its camera and whatever images the reply holds (rgb, depth, label)."""
        images = [a for a in (result.rgb, result.depth_m, result.label) if a is not None]
        if not images:
            raise ValueError("the render reply holds no image output")
        height, width = images[0].shape[:2]
        self.log_camera(
            entity, K, world_from_cam, width, height, rgb=result.rgb, depth_m=result.depth_m,
            label=result.label, texts=texts,
        )  # fmt: skip

    # -- points and objects -------------------------------------------------------------------

    def log_points(
        self,
        entity: str,
        xyz: np.ndarray,  # (N, 3) float32, world, metres
        *,
        colours: np.ndarray | None = None,  # (N, 3) uint8 or float in [0, 1]
        class_ids: np.ndarray | None = None,  # (N,) int >= 0 (annotation context class ids)
        radius_m: float = 0.02,
    ) -> None:
        """Points at ``entity`` (world metres), coloured per point or by class id."""
        pts = _array("xyz", xyz, (None, 3), np.float32)
        n = pts.shape[0]
        rgb = None
        if colours is not None:
            rgb = _array("colours", colours, (n, 3))
            if rgb.dtype != np.uint8:
                rgb = np.clip(np.round(np.asarray(rgb, np.float64) * 255.0), 0, 255).astype(np.uint8)
        ids = None if class_ids is None else _array("class_ids", class_ids, (n,), np.uint16)
        self.rec.log(entity, self._rr.Points3D(pts, colors=rgb, class_ids=ids, radii=radius_m))

    def log_objects(
        self, entity: str, objects: Sequence[ObjectCandidate], texts: Sequence[str]
    ) -> None:
        """Object candidates as axis-aligned boxes at ``entity`` (label: text, score, points; class
        id = index of the text in ``texts`` + 1) and their centroids at ``entity``'s sibling
        ``centroids``."""
        rr = self._rr
        index = {t: i for i, t in enumerate(texts)}
        lo = np.array([o.aabb_min for o in objects], np.float64).reshape(-1, 3)
        hi = np.array([o.aabb_max for o in objects], np.float64).reshape(-1, 3)
        labels = [f"{o.text} {o.score:.2f} ({o.n_points} pts)" for o in objects]
        ids = np.array([index.get(o.text, -1) + 1 for o in objects], np.uint16)
        self.rec.log(
            entity,
            rr.Boxes3D(centers=(lo + hi) / 2, half_sizes=(hi - lo) / 2, labels=labels, class_ids=ids),
        )
        parent = entity.rsplit("/", 1)[0] if "/" in entity else ""
        centroids = np.array([o.centroid for o in objects], np.float32).reshape(-1, 3)
        self.rec.log(
            f"{parent}/centroids" if parent else "centroids",
            rr.Points3D(centroids, labels=labels, class_ids=ids, radii=0.05),
        )

    def log_query(self, points: Points, texts: Sequence[str], *, entity: str = "world/query") -> None:
        """A ``query_points`` answer: ``entity/points`` coloured by score (viridis over the
        answer's score range, as the PLY of ``govnesf query --out``), ``entity/objects`` and
        ``entity/centroids``; on the ``map_version`` timeline at the answer's map version."""
        self.rec.set_time("map_version", sequence=int(points.map_version))
        self.rec.log(entity, self._rr.AnnotationContext(_annotation(texts)), static=True)
        self.log_points(
            f"{entity}/points", points.xyz, colours=score_colours(points.score),
            class_ids=np.maximum(np.asarray(points.label, np.int64), -1) + 1,
        )  # fmt: skip
        self.log_objects(f"{entity}/objects", points.objects, texts)

    def log_map(self, points: Points, texts: Sequence[str], *, entity: str = "world/map") -> None:
        """The semantic map (a ``query_points`` answer over the whole map, e.g. every class name
        without negatives): points coloured by label (class id label + 1, 0 = unlabelled)."""
        self.rec.set_time("map_version", sequence=int(points.map_version))
        self.rec.log(entity, self._rr.AnnotationContext(_annotation(texts)), static=True)
        label = np.asarray(points.label, np.int64)
        self.log_points(entity, points.xyz, colours=label_colours(label), class_ids=np.maximum(label, -1) + 1)
