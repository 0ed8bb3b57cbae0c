"""End-to-end demo (``make demo``): a synthetic recording, a real node process, replay, save.

Steps, each printed as it happens:

1. write a small synthetic recording: a camera circling a checkerboard floor, with the speed
   varying along the path (so some frames become keyframes and some do not), ray-cast RGB,
   metric depth and a tiny procedural feature map (``ov_space = "demo-checker"``);
2. start ``govnesf serve`` as a subprocess on free loopback ports, with the map directory under
   the output directory;
3. replay the recording into it and print the summary;
4. print the node's status, save the map, and check the saved file;
5. stop the node with SIGINT and check that it exited cleanly (exit code 0).

Outputs under ``out/demo/`` (override with ``--out``): the recording, the node log, the map.
A later stage replaces the synthetic recording with the simulated robot.

This module also provides the helpers the end-to-end tests and the benchmark share:
:func:`write_synthetic_recording`, :func:`synthetic_frame`, :func:`free_endpoints` and
:class:`NodeProcess`.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType

import numpy as np

from clients.client import MapperClient
from protocol.messages import Frame
from protocol.recording import RecordingWriter

REPO_ROOT = Path(__file__).resolve().parent.parent

# ---------------------------------------------------------------------------------------------
# synthetic frames: a camera circling a checkerboard floor (z = 0), looking at the origin

CHECKER_SIZE_M = 0.5
DEMO_OV_SPACE = "demo-checker"
DEMO_OV_DIM = 8


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cam for an OpenCV camera at ``eye`` (3,) looking at ``target`` (3,),
    world +z up (x right, y down, z forward in the camera)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    world_from_cam = np.eye(4)
    world_from_cam[:3, 0], world_from_cam[:3, 1], world_from_cam[:3, 2] = right, down, forward
    world_from_cam[:3, 3] = eye
    return world_from_cam


def render_floor(
    width: int, height: int, K: np.ndarray, world_from_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the checkerboard floor. Returns rgb (H, W, 3) uint8, depth_m (H, W) float32
    (0 where a ray misses the floor) and the floor cell parity (H, W) int (-1 = sky)."""
    fx, fy, cx, cy = K
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # pixel centres
    dirs_cam = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], axis=-1)  # (H, W, 3)
    dirs_world = dirs_cam @ world_from_cam[:3, :3].T
    eye = world_from_cam[:3, 3]
    dz = dirs_world[..., 2]
    hits = dz < -1e-6
    t = np.where(hits, -eye[2] / np.where(hits, dz, -1.0), 0.0)  # = depth along +z (dirs_cam z = 1)
    points = eye + t[..., None] * dirs_world
    cell = np.floor(points[..., :2] / CHECKER_SIZE_M).astype(np.int64)
    parity = np.where(hits, (cell[..., 0] + cell[..., 1]) % 2, -1)
    quadrant = (points[..., 0] > 0).astype(np.int64) + 2 * (points[..., 1] > 0)
    palette = np.array([[200, 60, 60], [60, 160, 60], [60, 90, 200], [210, 180, 60]], np.float64)
    base = palette[quadrant] * np.where(parity == 1, 1.0, 0.45)[..., None]
    shade = np.clip(1.0 - 0.04 * t, 0.4, 1.0)[..., None]  # darker with distance
    sky = np.array([150.0, 190.0, 235.0]) * (0.7 + 0.3 * (rows / height))[..., None]
    rgb = np.where(hits[..., None], base * shade, sky)
    depth_m = np.where(hits, t, 0.0).astype(np.float32)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth_m, parity


def synthetic_frame(
    seq: int,
    n_frames: int = 60,
    width: int = 160,
    height: int = 120,
    *,
    with_ov: bool = True,
    rgb_encoding: str = "rgb8",
) -> Frame:
    """Frame ``seq`` of a camera path once around the origin (radius 3 m, 1.5 m high), moving
    slowly near the start and end of the loop and fast in the middle."""
    phase = seq / max(n_frames, 1)
    angle = 2.0 * math.pi * (phase - math.sin(2.0 * math.pi * phase) / (2.0 * math.pi))
    eye = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.5])
    world_from_cam = look_at(eye, np.array([0.0, 0.0, 0.3]))
    K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
    rgb, depth_m, parity = render_floor(width, height, K, world_from_cam)
    ov = ov_space = None
    if with_ov:
        # A tiny stand-in for an OV feature map at 1/8 resolution: one-hot of (sky, dark, light).
        small = parity[4::8, 4::8]
        ov = np.zeros((*small.shape, DEMO_OV_DIM), np.float16)
        ov[..., 0] = small == -1
        ov[..., 1] = small == 0
        ov[..., 2] = small == 1
        ov_space = DEMO_OV_SPACE
    return Frame(
        seq=seq,
        stamp_ns=1_000_000_000 + seq * 100_000_000,  # 10 Hz
        width=width,
        height=height,
        K=K,
        world_from_cam=world_from_cam,
        rgb=rgb,
        depth_m=depth_m,
        ov=ov,
        ov_space=ov_space,
        rgb_encoding=rgb_encoding,
    )


def synthetic_frames(
    n_frames: int = 60, width: int = 160, height: int = 120, **kwargs: object
) -> Iterator[Frame]:
    for seq in range(n_frames):
        yield synthetic_frame(seq, n_frames, width, height, **kwargs)  # type: ignore[arg-type]


def write_synthetic_recording(
    path: str | Path, n_frames: int = 60, width: int = 160, height: int = 120, *, with_ov: bool = True
) -> Path:
    """Write ``n_frames`` synthetic frames to a ``.govrec`` file; returns its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"generator": "clients.demo", "scene": "checkerboard floor", "frames": n_frames}
    with RecordingWriter(path, meta) as writer:
        for frame in synthetic_frames(n_frames, width, height, with_ov=with_ov):
            writer.write(frame)
    return path


# ---------------------------------------------------------------------------------------------
# a node in a subprocess


def free_endpoints(count: int = 3) -> list[str]:
    """``count`` distinct ``tcp://127.0.0.1:PORT`` endpoints on currently free ports."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [f"tcp://127.0.0.1:{s.getsockname()[1]}" for s in sockets]
    finally:
        for s in sockets:
            s.close()


class NodeProcess:
    """``govnesf serve`` in a subprocess on free loopback ports; a context manager that always
    kills the process on exit. ``wait_ready()`` polls ``status`` until the node answers."""

    def __init__(
        self,
        map_dir: str | Path,
        *,
        log_path: str | Path | None = None,
        extra_args: Sequence[str] = (),
        events: bool = True,
    ) -> None:
        self.ingest, self.query, events_ep = free_endpoints(3)
        self.events: str | None = events_ep if events else None
        self.map_dir = Path(map_dir)
        self.log_path = Path(log_path) if log_path else None
        self.command = [
            sys.executable, "-m", "clients.cli", "serve",
            "--ingest", self.ingest, "--query", self.query, "--events", self.events or "",
            "--map-dir", str(self.map_dir), *extra_args,
        ]  # fmt: skip
        self.process: subprocess.Popen[bytes] | None = None
        self._log_file: object = None

    def start(self) -> NodeProcess:
        """Spawn the process (once; a second call does nothing)."""
        if self.process is not None:
            return self
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
        env.setdefault("HF_HUB_OFFLINE", "1")
        out = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        self._log_file = out
        self.process = subprocess.Popen(self.command, cwd=REPO_ROOT, env=env, stdout=out, stderr=out)
        return self

    def wait_ready(self, timeout_s: float = 20.0) -> None:
        """Block until the node answers ``status``; raise RuntimeError if it exits or times out."""
        deadline = time.monotonic() + timeout_s
        with MapperClient(ingest=self.ingest, query=self.query, timeout_s=0.25, retries=0) as client:
            while time.monotonic() < deadline:
                if self.process is not None and self.process.poll() is not None:
                    raise RuntimeError(
                        f"node exited with code {self.process.returncode} during start-up{self._log_hint()}"
                    )
                try:
                    client.status()
                    return
                except TimeoutError:
                    continue
        raise RuntimeError(f"node did not answer status within {timeout_s:g} s{self._log_hint()}")

    def _log_hint(self) -> str:
        return f" (log: {self.log_path})" if self.log_path else ""

    def client(self, **kwargs: object) -> MapperClient:
        """A client connected to this node."""
        return MapperClient(ingest=self.ingest, query=self.query, **kwargs)  # type: ignore[arg-type]

    def signal(self, signum: int = signal.SIGINT, timeout_s: float = 15.0) -> int:
        """Send ``signum`` and wait for the exit code."""
        assert self.process is not None
        self.process.send_signal(signum)
        return self.process.wait(timeout=timeout_s)

    def kill(self) -> None:
        """Make sure the process is gone (kills it if still running)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        if self._log_file not in (None, subprocess.DEVNULL):
            self._log_file.close()  # type: ignore[attr-defined]
            self._log_file = None

    def __enter__(self) -> NodeProcess:
        if self.process is None:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.kill()


# ---------------------------------------------------------------------------------------------
# the demo


def _step(n: int, text: str) -> None:
    print(f"\n[demo {n}/5] {text}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clients.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO_ROOT / "out" / "demo"), help="output directory")
    parser.add_argument("--frames", type=int, default=60, help="frames in the synthetic recording")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()

    from clients.client_cli import format_status
    from clients.replay import replay

    _step(1, f"writing a synthetic recording ({args.frames} frames, {args.width}x{args.height})")
    recording = write_synthetic_recording(out / "synthetic.govrec", args.frames, args.width, args.height)
    print(f"  {recording} ({recording.stat().st_size / 1e6:.1f} MB)")

    _step(2, "starting `govnesf serve` on free loopback ports")
    node = NodeProcess(out / "maps", log_path=out / "node.log")
    with node:  # starts the process, and kills it on the way out whatever happens
        node.wait_ready()
        print(f"  pid {node.process.pid if node.process else '?'}; ingest {node.ingest}, query {node.query}")
        print(f"  node log: {node.log_path}")

        _step(3, f"replaying {recording.name}")
        with node.client(timeout_s=10.0) as client:
            summary = replay(recording, client, window=8, progress=True)
            print("  " + "\n  ".join(summary.lines()))
            if summary.unreachable:
                print("demo FAILED: the node stopped answering", file=sys.stderr)
                return 1

            _step(4, "status, then save the map")
            status = client.status()
            print("  " + format_status(status).replace("\n", "\n  "))
            ok = client.save("demo")
            print(f"  {ok.message}")
            saved = node.map_dir / "demo.govmap"
            if not saved.is_file():
                print(f"demo FAILED: {saved} was not written", file=sys.stderr)
                return 1
            print(f"  {saved} ({saved.stat().st_size / 1e6:.1f} MB)")

        _step(5, "stopping the node with SIGINT")
        code = node.signal(signal.SIGINT)
        print(f"  node exited with code {code}")
        if code != 0:
            print(f"demo FAILED: node exit code {code} (see {node.log_path})", file=sys.stderr)
            return 1
    ok_frames = summary.sent == args.frames
    print(
        f"\ndemo finished in {time.monotonic() - started:.1f} s: {summary.sent}/{args.frames} frames acked, "
        f"{status.keyframes} keyframes in the window, map saved to {saved}"
    )
    return 0 if ok_frames else 1


if __name__ == "__main__":
    raise SystemExit(main())
