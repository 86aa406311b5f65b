"""``scalar-nerf-make-scene``: write one of the project's procedural scenes in nerfstudio format.

Scenes:
  town       a large town of streets and textured buildings (transforms.json, images/, depths/
             in mm: 16-bit PNGs, or .npy where a flight's ground lies beyond 65.5 m, scene.json),
             too large for one hash table: scalar-nerf splits it into blocks (automatic K > 1).
             --capture: a rig of street-level cameras on a vehicle (default), a walk, or a
             drone's aerial survey looking down.
  courtyard  the small courtyard of scalar-nerf-demo (transforms.json, images/)
  facade     a long wall painted with a random mural, photographed on a walk along it (transforms.json,
             images/): each camera sees a few metres of it, so a small hash table holds less of the wall
             than a block of it does

Train on it with every 8th frame held out:
  ns-train scalar-nerf --data DIR nerfstudio-data --eval-mode interval --eval-interval 8
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from pathlib import Path
from typing import Callable, List, NoReturn, Optional

PROG = "scalar-nerf-make-scene"
#: TownConfig fields whose command-line option has another name.
_OPTION = {"fov_x_deg": "fov"}


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad option in one line (exit 2), without the usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _number(kind: type, minimum: float, what: str, above: bool = False) -> Callable[[str], float]:
    """An argparse type: ``kind`` (int or float), finite and at least ``minimum`` (above it if
    ``above``); ``what`` says so in the error."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not (math.isfinite(value) and (value > minimum if above else value >= minimum)):
            raise argparse.ArgumentTypeError(f"{text} must be {what}")
        return value

    return parse


_positive_int = _number(int, 1, "a positive integer")
_non_negative_int = _number(int, 0, "0 or more")
_positive_float = _number(float, 0.0, "a positive number", above=True)


def build_parser() -> argparse.ArgumentParser:
    """The command's options."""
    parser = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", choices=("town", "courtyard", "facade"), default="town", help="which scene (default: town)")
    parser.add_argument("--output", "-o", type=Path, required=True, help="scene folder to write (created; must be empty unless --overwrite)")
    parser.add_argument("--num-images", type=_positive_int, default=None, help="frames (town: 300, courtyard: 40, facade: 48)")
    parser.add_argument("--width", type=_positive_int, default=None, help="image width in pixels (town: 320, courtyard: 160, facade: 96)")
    parser.add_argument("--height", type=_positive_int, default=None, help="image height in pixels (town: 240, courtyard: 120, facade: 72)")
    parser.add_argument("--seed", type=_non_negative_int, default=0, help="random seed; the same seed writes byte-identical files (default 0)")
    town = parser.add_argument_group("town only")
    town.add_argument("--blocks-x", type=_positive_int, default=None, help="city blocks along x (default 4)")
    town.add_argument("--blocks-y", type=_positive_int, default=None, help="city blocks along y (default 3)")
    town.add_argument("--extent", type=_positive_float, default=None, help="street grid of about this many metres on each side (sets --blocks-x and --blocks-y)")
    town.add_argument("--block-size", type=_positive_float, default=None, help="side of a city block in metres (default 40)")
    town.add_argument("--street-width", type=_positive_float, default=None, help="building line to building line in metres (default 14)")
    town.add_argument("--road-width", type=_positive_float, default=None, help="asphalt width in metres (default 8, or street width - 6 for narrower streets)")
    town.add_argument("--fov", type=_positive_float, default=None, help="horizontal field of view in degrees (default 45)")
    town.add_argument("--capture", choices=("rig", "walk", "aerial", "aerial+rig"), default=None,
                      help="rig: a vehicle's cameras each take a frame at evenly spaced stops (default); walk: one frame per "
                           "position, random heading; aerial: a drone flies parallel lines over the town, looking down; "
                           "aerial+rig: the first half of the frames from the drone, the rest from the rig")
    town.add_argument("--aerial-altitude", type=_positive_float, default=None, help="aerial captures only: flight altitude in metres (default 55)")
    town.add_argument("--rig-headings", type=float, nargs="+", default=None, metavar="DEG",
                      help="rig cameras' headings in degrees from the driving direction, positive to the left (default 30 -30)")
    town.add_argument("--supersample", type=_positive_int, default=None, help="colour samples per pixel along each axis (default 1)")
    town.add_argument("--textures", choices=("filtered", "point-sampled"), default=None,
                      help="filtered: each sample averages the detail finer than the surface it covers, as a camera does, and "
                           "the ground and roofs carry weathering (default); "
                           "point-sampled: the colour at each sample's point (generator version 2's pixels)")
    town.add_argument("--photos", type=Path, default=None, metavar="DIR",
                      help="also write the frames to DIR as JPEG photos with their camera's GPS position and focal length in the EXIF "
                           "(for trying scalar-nerf-process-data on a capture of known poses)")
    town.add_argument("--workers", type=_positive_int, default=1, help="processes rendering frames at once (same output; default 1)")
    facade = parser.add_argument_group("facade only")
    facade.add_argument("--wall-length", type=_positive_float, default=None, help="length of the wall in metres (default 40)")
    parser.add_argument("--overwrite", action="store_true", help="write into a non-empty folder, replacing an earlier scene's frames")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return parser


def _refuse(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    parser.exit(1, f"{parser.prog}: error: {message}\n")


def _check_output(parser: argparse.ArgumentParser, output: Path, overwrite: bool, option: str = "--output") -> None:
    """Refuse an output (the folder of ``option``) that is a file, a non-empty folder (without --overwrite)
    or not writable (exit status 1: the options are well formed, the folder is not usable)."""
    import os

    if output.exists() and not output.is_dir():
        _refuse(parser, f"{option} {output} exists and is not a folder")
    if output.is_dir():
        if any(output.iterdir()) and not overwrite:
            _refuse(parser, f"{option} {output} is not empty (pass --overwrite to write into it)")
        if not os.access(output, os.W_OK | os.X_OK):
            _refuse(parser, f"{option} {output} is not writable")
        return
    parent = output.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        _refuse(parser, f"{option} {output} cannot be created: {parent} is not a writable folder")


def _option_message(error: ValueError) -> str:
    """``error``'s message naming the command-line option, not the TownConfig field."""
    return re.sub(r"TownConfig\.(\w+)", lambda m: "--" + _OPTION.get(m.group(1), m.group(1)).replace("_", "-"), str(error))


def _town(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from scalar_nerfstudio.scenes.town import TownConfig, blocks_for_extent, build_town, town_camera_poses, write_town
    from scalar_nerfstudio.scenes.town.photos import write_photos

    _refuse_options_of_other_scenes(args, parser)
    options = {}
    for key, name in (("num_images", "num_images"), ("width", "width"), ("height", "height"), ("block_size", "block_size"),
                      ("street_width", "street_width"), ("road_width", "road_width"), ("fov", "fov_x_deg"), ("supersample", "supersample"),
                      ("textures", "textures")):
        if getattr(args, key) is not None:
            options[name] = getattr(args, key)
    if args.capture is not None:
        options["capture"] = args.capture
    if args.rig_headings is not None:
        options["rig_headings"] = tuple(args.rig_headings)
    if args.aerial_altitude is not None:
        if args.capture not in ("aerial", "aerial+rig"):
            parser.error("--aerial-altitude: only with --capture aerial or aerial+rig")
        options["aerial_altitude"] = args.aerial_altitude
    if args.street_width is not None and args.road_width is None:
        options["road_width"] = max(2.0, min(TownConfig.road_width, args.street_width - 6.0))
    if args.extent is not None:
        if args.blocks_x is not None or args.blocks_y is not None:
            parser.error("--extent sets the number of blocks; give either --extent or --blocks-x/--blocks-y")
        base = TownConfig(**{k: v for k, v in options.items() if k in ("block_size", "street_width")})
        options["blocks_x"] = options["blocks_y"] = blocks_for_extent(args.extent, base.block_size, base.street_width)
    if args.blocks_x is not None:
        options["blocks_x"] = args.blocks_x
    if args.blocks_y is not None:
        options["blocks_y"] = args.blocks_y
    try:
        config = TownConfig(seed=args.seed, **options)
    except ValueError as error:
        parser.error(_option_message(error))
    _check_output(parser, args.output, args.overwrite)
    if args.photos is not None:
        _check_output(parser, args.photos, args.overwrite, option="--photos")
    start = time.perf_counter()
    try:
        path = write_town(args.output, config, progress=not args.quiet, overwrite=args.overwrite, workers=args.workers)
    except (FileExistsError, PermissionError) as error:
        parser.error(str(error))
    except ValueError as error:  # a capture that cannot be flown over this town (nothing written)
        parser.error(_option_message(error))
    photos = write_photos(args.output, args.photos) if args.photos is not None else 0
    seconds = time.perf_counter() - start
    if not args.quiet:
        town = build_town(config)
        sx, sy = config.extent
        print(
            f"Wrote {config.num_images} frames of {config.width}x{config.height} of a {config.blocks_x}x{config.blocks_y}-block town "
            f"({sx:.0f} x {sy:.0f} m, {town.num_buildings} buildings) to {path.parent} in {seconds:.1f} s."
        )
        print(_automatic_blocks_line(config, town_camera_poses(town)))
        if photos:
            print(f"Wrote {photos} JPEG photos with GPS and focal length in their EXIF to {args.photos}: "
                  f"scalar-nerf-process-data --images {args.photos} --output <folder>")
        print(f"Train: ns-train scalar-nerf --data {path.parent} nerfstudio-data --eval-mode interval --eval-interval 8")
    return 0


def _automatic_blocks_line(config, poses) -> str:
    """scalar-nerf's automatic K for this capture (every 8th frame held out, T = 2^19)."""
    import numpy as np

    from scalar_nerfstudio.blocks.capacity import auto_num_blocks, layout_scale

    train = poses[np.arange(len(poses)) % 8 != 0]
    if len(train) == 0:
        return "Automatic K: no training frame with every 8th held out."
    scale = layout_scale(train[:, :3, 3], -train[:, :3, 2], np.full(len(train), config.focal_px))
    k = auto_num_blocks(scale, log2_hashmap_size=19, num_images=len(train), min_images_per_block=6, max_blocks=8)
    return f"scalar-nerf's automatic K for this capture (eval interval 8, T = 2^19): {k} (layout R = {scale.layout_pixels:.0f} px)."


_TOWN_ONLY = ("blocks_x", "blocks_y", "extent", "block_size", "street_width", "road_width", "fov", "supersample", "textures", "capture",
              "rig_headings", "aerial_altitude", "photos")


def _refuse_options_of_other_scenes(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    for scene, names in (("town", _TOWN_ONLY), ("facade", ("wall_length",))):
        given = [f"--{name.replace('_', '-')}" for name in names if getattr(args, name) is not None]
        if given and args.scene != scene:
            parser.error(f"{', '.join(given)}: only for --scene {scene}")


def _courtyard(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from scalar_nerfstudio.scenes.courtyard import write_scene

    _refuse_options_of_other_scenes(args, parser)
    _check_output(parser, args.output, args.overwrite)
    start = time.perf_counter()
    path = write_scene(args.output, num_images=args.num_images or 40, width=args.width or 160, height=args.height or 120, seed=args.seed)
    if not args.quiet:
        print(f"Wrote the courtyard ({args.num_images or 40} frames) to {path.parent} in {time.perf_counter() - start:.1f} s.")
    return 0


def _facade(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    from scalar_nerfstudio.scenes.facade import write_scene

    _refuse_options_of_other_scenes(args, parser)
    _check_output(parser, args.output, args.overwrite)
    start = time.perf_counter()
    frames, length = args.num_images or 48, args.wall_length or 40.0
    path = write_scene(args.output, num_images=frames, width=args.width or 96, height=args.height or 72, length=length, seed=args.seed)
    if not args.quiet:
        print(f"Wrote the facade ({frames} frames along {length:g} m of wall) to {path.parent} in {time.perf_counter() - start:.1f} s.")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    """Parse ``argv`` (default: the command line) and write the scene; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.scene == "town":
            return _town(args, parser)
        if args.scene == "facade":
            return _facade(args, parser)
        return _courtyard(args, parser)
    except OSError as error:  # e.g. the disk filled up or the folder vanished while writing
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1


def entrypoint() -> None:
    """Console script entry point."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
