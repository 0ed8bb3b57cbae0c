"""``govnesf import FORMAT PATH --out FILE.govrec``: convert a dataset folder to a recording."""

from __future__ import annotations

import argparse
import sys

from clients.cli.args import positive_int
from clients.importers.base import UP_AXES, DatasetReader, ImporterError, ReaderOptions, parse_K
from clients.importers.convert import RGB_ENCODINGS, convert
from clients.importers.registry import ALIASES, FORMATS, open_dataset
from clients.importers.rosbag import POSE_AXES, POSE_INTERP, RosbagOptions, RosbagReader


def build_parser() -> argparse.ArgumentParser:
    formats = "\n".join(
        [f"  {name:<8} {reader.description}" for name, reader in FORMATS.items()]
        + [f"  {alias:<8} same as {target}" for alias, target in ALIASES.items()]
    )
    parser = argparse.ArgumentParser(
        prog="govnesf import",
        description="Convert a dataset folder to a .govrec recording (see docs/how-to/import.md).",
        epilog=f"formats:\n{formats}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "format", choices=[*FORMATS, *ALIASES], metavar="FORMAT", help="dataset layout: %(choices)s"
    )
    parser.add_argument("path", metavar="PATH", help="dataset folder (scene / sequence)")
    parser.add_argument("--out", required=True, metavar="FILE.govrec", help="recording to write")
    parser.add_argument(
        "--stride",
        type=positive_int,
        default=1,
        metavar="N",
        help="take every N-th source frame (default 1)",
    )
    parser.add_argument(
        "--max-frames", type=positive_int, default=None, metavar="N", help="stop after writing N frames"
    )
    parser.add_argument(
        "--rgb-encoding",
        choices=RGB_ENCODINGS,
        default="rgb8",
        help="colour encoding in the recording (default rgb8)",
    )
    parser.add_argument(
        "--depth", action=argparse.BooleanOptionalAction, default=True, help="import depth (default: yes)"
    )
    parser.add_argument(
        "--K",
        dest="K",
        metavar="fx,fy,cx,cy",
        default=None,
        help="override intrinsics, in the dataset's own convention (pixel centres at integers)",
    )
    parser.add_argument(
        "--fps", type=float, default=30.0, help="frame rate for synthesised timestamps (default 30)"
    )
    parser.add_argument(
        "--up-axis",
        choices=list(UP_AXES),
        default=None,
        help="axis of the dataset's world that points up, rotated to +z (default: per format; "
        "7scenes and open3d -y, others z)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace FILE.govrec if it exists")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    ros = parser.add_argument_group("rosbag options (FORMAT rosbag only; docs/how-to/import.md)")
    for flag, meta, text in ROSBAG_FLAGS:
        ros.add_argument(flag, metavar=meta, default=None, help=text)
    ros.add_argument("--max-dt", type=float, default=None, metavar="S",
                     help="largest time between an image and its depth image / pose samples (default 0.05)")
    ros.add_argument("--pose-interp", choices=POSE_INTERP, default=None,
                     help="pose at the image stamp: interpolated (linear, default) or the nearest sample")
    ros.add_argument("--pose-axes", choices=POSE_AXES, default=None,
                     help="axes of --pose-topic's frame: optical (x right, y down, z forward; default) or "
                          "body (REP 103 x forward, y left, z up)")  # fmt: skip
    return parser


ROSBAG_FLAGS = (
    ("--image-topic", "TOPIC", "colour topic (Image or CompressedImage; default: the only one)"),
    ("--depth-topic", "TOPIC", "depth topic (Image 16UC1 mm / 32FC1 m; default: the one named *depth*)"),
    ("--camera-info-topic", "TOPIC", "CameraInfo topic (default: IMAGE_NS/camera_info, or the only one)"),
    ("--pose-topic", "TOPIC", "PoseStamped / PoseWithCovarianceStamped / Odometry topic (default: TF)"),
    ("--world-frame", "FRAME", "TF frame the poses are in (default map; with --pose-topic: its frame_id)"),
    ("--camera-frame", "FRAME", "TF frame of the camera (default: the images' header.frame_id)"),
)


def rosbag_options(args: argparse.Namespace) -> RosbagOptions | None:
    """The rosbag options given on the command line (None when none was given)."""
    names = [flag[2:].replace("-", "_") for flag, _, _ in ROSBAG_FLAGS]
    given = {name: getattr(args, name) for name in names}
    given.update(max_dt_s=args.max_dt, pose_interp=args.pose_interp, pose_axes=args.pose_axes)
    given = {k: v for k, v in given.items() if v is not None}
    return RosbagOptions(**given) if given else None


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``govnesf import``; returns the exit status (0 ok, 1 import error, 2 usage)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    ros = rosbag_options(args)
    if ros is not None and ALIASES.get(args.format, args.format) != RosbagReader.format_name:
        parser.error(f"the rosbag options do not apply to format {args.format}")
    try:
        options = ReaderOptions(
            K=parse_K(args.K) if args.K is not None else None,
            load_depth=args.depth,
            fps=args.fps,
            up_axis=args.up_axis,
        )
        if ALIASES.get(args.format, args.format) == RosbagReader.format_name:
            reader: DatasetReader = RosbagReader(args.path, options, ros)
        else:
            reader = open_dataset(args.format, args.path, options)
        summary = convert(
            reader,
            args.out,
            stride=args.stride,
            max_frames=args.max_frames,
            rgb_encoding=args.rgb_encoding,
            with_depth=args.depth,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
    except ImporterError as exc:
        print(f"govnesf import: error: {exc}", file=sys.stderr)
        return 1
    print(summary.format())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
