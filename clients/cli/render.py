"""``govnesf render``: render a view of a node's map from any pose and write PNGs.

Examples::

    govnesf render --pose "1.0,2.0,1.3,90,-10" --width 160 --height 120 --texts chair table --out view.png
    govnesf render --pose-matrix 0 0 1 1  -1 0 0 2  0 -1 0 1.5  0 0 0 1 --out view.png --separate

``--pose "x,y,z,yaw_deg,pitch_deg"``: camera centre in the world (metres, +z up); yaw about +z from
the world +x axis (90 looks along +y), pitch up from the horizontal; no roll. ``--pose-matrix``
takes the 16 numbers of ``world_from_cam`` (camera-to-world, OpenCV optical frame) row-major.
Intrinsics follow from ``--hfov`` (pinhole, square pixels, principal point at the centre) or are
given with ``--K fx fy cx cy``.

Output: one PNG with the panels side by side -- colour | depth (colormapped, near = yellow,
far = dark, no depth = black) | semantic labels (one colour per text, black = nothing rendered,
with a legend underneath) when ``--texts`` are given. ``--separate`` also writes
``NAME_rgb.png``, ``NAME_depth.png`` and ``NAME_label.png``; ``--npz`` the raw arrays;
``--rerun F.rrd`` logs the view (its camera, rgb, depth, labels) for the Rerun viewer.

Exit codes: 0 success, 1 the node did not answer, 2 invalid arguments, 3 the node answered
with an error. Before the render the node is asked for its status with ``--ping-timeout``
(default 2 s, no retry): with no node at ``--query`` the command fails then, not after the
render's ``--timeout``; ``--ping-timeout 0`` skips the check.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from clients.cli.args import add_ping_argument, late_reply_message, ping_first
from clients.client import (
    DEFAULT_QUERY,
    MapperClient,
    NodeUnreachableError,
    add_curve_arguments,
    curve_from_args,
)
from clients.colors import LABEL_COLORS, colorize_depth, colorize_labels
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import RenderResult, Status

__all__ = [
    "LABEL_COLORS",
    "colorize_depth",
    "colorize_labels",
    "compose_panels",
    "main",
    "pose_from_xyz_yaw_pitch",
]

def pose_from_xyz_yaw_pitch(x: float, y: float, z: float, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """(4, 4) world_from_cam of a level camera (no roll) at (x, y, z) looking along yaw/pitch.

    >>> np.round(pose_from_xyz_yaw_pitch(1, 2, 1.5, 0, 0), 6).tolist()[:3]
    [[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 2.0], [0.0, -1.0, 0.0, 1.5]]
    """
    if not -89.9 <= pitch_deg <= 89.9:
        raise ValueError(
            f"pitch_deg {pitch_deg} out of range -89.9..89.9 (a camera looking straight up/down has no yaw)"
        )
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, (x, y, z)
    return pose + 0.0  # no negative zeros


def _legend(texts: list[str], label: np.ndarray, width: int, scale: int) -> np.ndarray:
    from PIL import Image, ImageDraw

    row_h = 12 * scale
    img = Image.new("RGB", (width, row_h * (len(texts) + 1) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    total = max(label.size, 1)
    for i, text in enumerate(texts):
        y = 2 + i * row_h
        colour = tuple(int(c) for c in LABEL_COLORS[i % len(LABEL_COLORS)])
        draw.rectangle([2, y + 1, 2 + row_h - 3, y + row_h - 2], fill=colour)
        share = 100.0 * float((label == i).sum()) / total
        draw.text((row_h + 4, y), f"{i}: {text} ({share:.0f}%)", fill=(0, 0, 0))
    y = 2 + len(texts) * row_h
    draw.rectangle([2, y + 1, 2 + row_h - 3, y + row_h - 2], fill=(0, 0, 0))
    draw.text(
        (row_h + 4, y),
        f"-1: nothing rendered ({100.0 * float((label < 0).sum()) / total:.0f}%)",
        fill=(0, 0, 0),
    )
    return np.asarray(img)


def compose_panels(result: RenderResult, texts: list[str] | None, scale: int = 1) -> dict[str, np.ndarray]:
    """The panels present in ``result`` as (H', W', 3) uint8 images (upscaled by ``scale``),
    plus ``"combined"`` (side by side, legend under the label panel)."""
    panels: dict[str, np.ndarray] = {}
    if result.rgb is not None:
        panels["rgb"] = result.rgb
    if result.depth_m is not None:
        panels["depth"] = colorize_depth(result.depth_m)
    if result.label is not None:
        panels["label"] = colorize_labels(result.label)
    panels = {k: np.repeat(np.repeat(v, scale, axis=0), scale, axis=1) for k, v in panels.items()}
    if not panels:
        raise ValueError("the render reply holds no image output")
    columns = []
    height = max(p.shape[0] for p in panels.values())
    legend = None
    if result.label is not None and texts:
        legend = _legend(texts, result.label, panels["label"].shape[1], max(1, scale // 2 + 1))
        height = max(height, panels["label"].shape[0] + legend.shape[0])
    for name, panel in panels.items():
        column = np.full((height, panel.shape[1], 3), 255, np.uint8)
        column[: panel.shape[0]] = panel
        if name == "label" and legend is not None:
            column[panel.shape[0] : panel.shape[0] + legend.shape[0], : legend.shape[1]] = legend[
                :, : panel.shape[1]
            ]
        columns.append(column)
        columns.append(np.full((height, 4, 3), 255, np.uint8))
    combined = np.concatenate(columns[:-1], axis=1)
    out = dict(panels)
    out["combined"] = combined
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="govnesf render", description="Render a view of a node's map and write PNGs."
    )
    pose = p.add_mutually_exclusive_group(required=True)
    pose.add_argument("--pose", metavar="X,Y,Z,YAW,PITCH", help="camera centre (m) and yaw/pitch (degrees)")
    pose.add_argument(
        "--pose-matrix", nargs=16, type=float, metavar="V", help="world_from_cam, 16 numbers row-major"
    )
    p.add_argument("--width", type=int, default=160, help="image width in pixels (160)")
    p.add_argument("--height", type=int, default=120, help="image height in pixels (120)")
    p.add_argument("--hfov", type=float, default=70.0, metavar="DEG", help="horizontal field of view (70)")
    p.add_argument(
        "--K", nargs=4, type=float, metavar=("FX", "FY", "CX", "CY"), help="intrinsics instead of --hfov"
    )
    p.add_argument("--texts", nargs="+", metavar="TEXT", help="label set: adds the semantic panel")
    p.add_argument("--out", default="view.png", help="combined PNG (view.png)")
    p.add_argument("--separate", action="store_true", help="also write NAME_rgb/_depth/_label.png")
    p.add_argument("--npz", metavar="FILE", help="also save the raw arrays (rgb, depth_m, label, score)")
    p.add_argument("--scale", type=int, default=1, help="upscale the PNGs by this integer factor (1)")
    p.add_argument(
        "--rerun", metavar="FILE.rrd", help="also log the view and its camera for the Rerun viewer"
    )
    from clients.rerun_log import CONNECT_HELP  # no rerun import: only the help text

    p.add_argument("--rerun-connect", metavar="ADDR", help=CONNECT_HELP)
    p.add_argument(
        "--query", default=DEFAULT_QUERY, metavar="EP", help=f"node query endpoint ({DEFAULT_QUERY})"
    )
    p.add_argument(
        "--timeout", type=float, default=120.0, metavar="S", help="seconds to wait for the render (120)"
    )
    p.add_argument("--retries", type=int, default=0, metavar="N", help="retries before giving up (0)")
    add_ping_argument(p)
    add_curve_arguments(p)
    return p


def _camera(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    if args.pose is not None:
        parts = [s for s in args.pose.replace(" ", "").split(",") if s]
        if len(parts) != 5:
            raise ValueError(
                f"--pose needs 5 comma-separated numbers x,y,z,yaw_deg,pitch_deg, got {args.pose!r}"
            )
        values = [float(v) for v in parts]
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"--pose values must be finite, got {args.pose!r}")
        world_from_cam = pose_from_xyz_yaw_pitch(*values)
    else:
        world_from_cam = np.asarray(args.pose_matrix, dtype=np.float64).reshape(4, 4)
    if not (1 <= args.width <= 4096 and 1 <= args.height <= 4096):
        raise ValueError(f"--width/--height {args.width}x{args.height} out of range 1..4096")
    if args.K is not None:
        K = np.asarray(args.K, dtype=np.float64)
    else:
        if not 1.0 <= args.hfov <= 179.0:
            raise ValueError(f"--hfov {args.hfov} out of range 1..179 degrees")
        f = args.width / 2 / math.tan(math.radians(args.hfov) / 2)
        K = np.array([f, f, args.width / 2, args.height / 2])
    if args.scale < 1 or args.scale > 16:
        raise ValueError(f"--scale {args.scale} out of range 1..16")
    return K, world_from_cam


def _write_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    prog = "govnesf render"
    try:
        K, world_from_cam = _camera(args)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if args.rerun or args.rerun_connect:  # a bad path / no viewer is an error before the render
        from clients.rerun_log import RerunLogError, check_rerun_outputs

        try:
            check_rerun_outputs(args.rerun, args.rerun_connect)
        except RerunLogError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 2
    outputs = ["rgb", "depth"] + (["label", "score"] if args.texts else [])
    pinged: Status | None = None
    try:
        curve = curve_from_args(args)
        with MapperClient(
            query=args.query, timeout_s=args.timeout, retries=args.retries, curve=curve
        ) as client:
            pinged = ping_first(client, args)
            result = client.render(args.width, args.height, K, world_from_cam, outputs, args.texts)
    except NodeUnreachableError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    except TimeoutError as exc:
        print(f"{prog}: {late_reply_message(exc, args, pinged is not None)}", file=sys.stderr)
        return 1
    except RemoteError as exc:
        print(f"{prog}: the node refused: {exc.code}: {exc.message}", file=sys.stderr)
        return 3
    except ProtocolError as exc:  # the request was invalid before sending (e.g. a bad pose matrix)
        print(f"{prog}: {exc.message}", file=sys.stderr)
        return 2
    panels = compose_panels(result, args.texts, scale=args.scale)
    out = Path(args.out)
    _write_png(out, panels["combined"])
    written = [str(out)]
    if args.separate:
        for name in ("rgb", "depth", "label"):
            if name in panels:
                path = out.with_name(f"{out.stem}_{name}{out.suffix or '.png'}")
                _write_png(path, panels[name])
                written.append(str(path))
    if args.npz:
        arrays = {k: v for k, v in (("rgb", result.rgb), ("depth_m", result.depth_m), ("label", result.label),
                                     ("score", result.score)) if v is not None}  # fmt: skip
        np.savez_compressed(args.npz, **arrays)  # type: ignore[arg-type]
        written.append(args.npz)
    if args.rerun or args.rerun_connect:
        from clients.rerun_log import RerunLog, RerunLogError

        try:
            with RerunLog(args.rerun, connect=args.rerun_connect, recording_name="govnesf render") as rlog:
                rlog.log_render(result, K, world_from_cam, args.texts)
        except RerunLogError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 1
        written += [args.rerun] if args.rerun else []
        written += [f"the Rerun viewer at {rlog.url}"] if args.rerun_connect else []
    timing = result.timing_ms.get("handler", result.timing_ms.get("total"))
    print(f"rendered {args.width}x{args.height}" + (f" in {timing:.0f} ms" if timing is not None else ""))
    if result.depth_m is not None and (result.depth_m > 0).any():
        d = result.depth_m[result.depth_m > 0]
        print(f"depth: {100.0 * d.size / result.depth_m.size:.0f}% of pixels, {d.min():.2f}..{d.max():.2f} m")
    if result.label is not None and result.score is not None and args.texts:
        for i, text in enumerate(args.texts):
            share = 100.0 * float((result.label == i).sum()) / result.label.size
            print(f"  {text!r}: {share:.1f}% of pixels, max score {float(result.score[..., i].max()):.3f}")
    print("wrote " + ", ".join(written))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
