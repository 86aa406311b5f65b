"""``scalar-nerf-export-frame``: map a mesh or point cloud from a run's model frame to the capture's frame.

ns-export's tsdf and poisson meshes (and point clouds exported without --save-world-frame True) are
in the run's normalised model frame. This writes a copy in the frame of the scene's transforms.json
(for scalar-nerf-process-data scenes: the capture's frame, metres east-north-up when the photos
had GPS), using the run's dataparser_transforms.json:

  scalar-nerf-export-frame --load-config RUN/config.yml --input exports/mesh.ply --output mesh_world.ply

.ply (ascii or binary; vertex x, y, z and nx, ny, nz are mapped, everything else is kept) and .obj
(v and vn lines) files.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, NoReturn, Optional

from scalar_nerfstudio.process.errors import ProcessDataError
from scalar_nerfstudio.process.export_frame import find_transforms, map_file, read_transform

PROG = "scalar-nerf-export-frame"


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad option in one line (exit 2), without the usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="the run's config.yml (its folder holds dataparser_transforms.json)")
    parser.add_argument("--input", type=Path, required=True, help=".ply or .obj written by ns-export (model frame)")
    parser.add_argument("--output", type=Path, required=True, help="file to write (same ending as --input), in the capture's frame")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        transforms = find_transforms(args.load_config)
        count = map_file(args.input, args.output, read_transform(transforms))
    except ProcessDataError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1
    except OSError as error:  # an unwritable --output, a full disk
        print(f"{PROG}: error: {error.strerror or error} ({error.filename or args.output}); nothing was written", file=sys.stderr)
        return 1
    print(f"wrote {args.output} ({count} vertices mapped to the capture's frame with {transforms})")
    return 0


def entrypoint() -> None:
    """Console script."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
