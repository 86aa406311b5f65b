"""``scalar-nerf-process-data``: photos -> a nerfstudio scene, poses by structure-from-motion (pycolmap, CPU).

  scalar-nerf-process-data --images PHOTOS --output SCENE

Stages: check the photos; SIFT features on each photo resized to --max-image-size; match pairs
(--matching); mapping (--mapper: incremental, or global for large captures); write
SCENE/transforms.json (OPENCV camera, OpenGL axes), SCENE/images/ (the registered photos,
hard-linked or copied), SCENE/images_2, _4, _8 and SCENE/sparse_pc.ply. With EXIF GPS in every
photo the scene is in metres, east-north-up about the photos' mean position; without, in COLMAP's
units with +z along the cameras' mean up direction.

Photos of several cameras or sizes each get their camera's own intrinsics (per frame in
transforms.json). A photo that cannot be read or is not registered is left out and named.

SCENE/colmap keeps the database and the reconstruction: run the same command again to resume
(finished stages are skipped); --overwrite starts over. The photos are only read.

Needs pycolmap:  pip install "scalar-nerfstudio[process]"
Then:            ns-train scalar-nerf --data SCENE
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Dict, Iterator, List, NoReturn, Optional, Tuple

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from scalar_nerfstudio.process import align, scene
from scalar_nerfstudio.process.errors import ProcessDataError
from scalar_nerfstudio.process.photos import PhotoSet, inspect_photos, list_photos

try:
    from scalar_nerfstudio.process import sfm
except ImportError as _error:  # pycolmap is the optional "process" extra
    sfm = None
    _IMPORT_ERROR = str(_error)

PROG = "scalar-nerf-process-data"
MATCHING = ("auto", "spatial", "sequential", "exhaustive")
MAPPERS = ("auto", "incremental", "global", "hierarchical")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad option in one line (exit 2), without the usage block."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command's options."""
    parser = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=Path, required=True, help="folder of photos (.jpg, .jpeg, .png, .tif; read only, sub-folders ignored)")
    parser.add_argument("--output", "-o", type=Path, required=True, help="scene folder to write (new, or one this command wrote: it resumes)")
    parser.add_argument("--max-image-size", type=_positive_int, default=1000,
                        help="features are found on each photo resized so its long side is at most this many pixels (default 1000)")
    parser.add_argument("--matching", choices=MATCHING, default="auto",
                        help="pairs to match: spatial (nearest photos by EXIF GPS), sequential (next photos by file name), "
                             "exhaustive (all pairs); auto: spatial if every photo has GPS, else exhaustive up to 50 photos, else sequential")
    parser.add_argument("--mapper", choices=MAPPERS, default="auto",
                        help="how the poses are solved from the matches: incremental (one photo at a time: robust, "
                             "its time grows fast with the photos), global (GLOMAP: all at once, for thousands of "
                             "photos), hierarchical (incremental on overlapping clusters, merged); auto: incremental "
                             "below 300 photos, else global")
    parser.add_argument("--spatial-neighbors", type=_positive_int, default=20, help="spatial: photos each photo is matched with (default 20)")
    parser.add_argument("--sequential-overlap", type=_positive_int, default=10, help="sequential: following photos each photo is matched with (default 10)")
    parser.add_argument("--threads", type=int, default=-1, help="CPU threads for COLMAP and for writing images (-1: all cores)")
    parser.add_argument("--overwrite", action="store_true", help="delete what an earlier run wrote into --output (database included) and start over")
    return parser


@contextmanager
def _progress(console: Console) -> Iterator[Progress]:
    columns = (SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        yield progress


def _done(progress: Progress, description: str) -> None:
    """A finished stage's line (no clock running)."""
    progress.update(progress.add_task(description, total=1), completed=1)


def _stage(progress: Progress, description: str, total: Optional[int]):
    task = progress.add_task(description, total=total)
    return task, (lambda n=1: progress.advance(task, n)), progress.refresh


def _missing_pycolmap() -> str:
    return f"pycolmap is not installed ({_IMPORT_ERROR}); install it with: pip install \"scalar-nerfstudio[process]\""


def run(args: argparse.Namespace, err: Console) -> int:
    """The stages (progress bars on ``err``, the summary on stdout); raises ProcessDataError for bad input."""
    if sfm is None:  # main() says so first; a direct call is told the same
        raise ProcessDataError(_missing_pycolmap())
    started = time.monotonic()
    workers = (os.cpu_count() or 1) if args.threads < 1 else args.threads
    if not args.images.is_dir():
        raise ProcessDataError(f"{args.images}: no such folder of photos")
    scene.check_output(args.output, args.images)
    options = sfm.SfmOptions(
        max_image_size=args.max_image_size, matching=args.matching, spatial_neighbors=args.spatial_neighbors,
        sequential_overlap=args.sequential_overlap, num_threads=args.threads,
    )
    timings = {}
    with _progress(err) as progress:
        _, advance, _ = _stage(progress, "checking photos", len(list_photos(args.images)) or None)
        photos = inspect_photos(args.images, progress=advance, workers=workers)
        for _, why in photos.unreadable:
            err.print(f"left out {why}", markup=False, highlight=False, soft_wrap=True)
        matching = sfm.resolve_matching(args.matching, photos)
        mapper = sfm.resolve_mapper(args.mapper, len(photos.photos))
        if args.overwrite:
            scene.remove_outputs(args.output)
        workspace, stages = sfm.open_workspace(args.output / "colmap", photos, options)
        sfm.quiet_colmap()

        if stages["extracted"]:
            _done(progress, "features: done earlier")
        else:
            _, advance, _ = _stage(progress, f"features (SIFT, long side {args.max_image_size} px)", len(photos.names))
            clock = time.monotonic()
            sfm.extract_features(workspace, photos, options=options, advance=advance)
            timings["features"] = time.monotonic() - clock
            stages["extracted"] = True
            workspace.write_stages(stages)

        if matching in stages["matched"]:
            _done(progress, f"matching ({matching}): done earlier")
        else:
            pairs = sfm.count_pairs(workspace, matching, options)
            task, _, tick = _stage(progress, f"matching {pairs} pairs ({matching})", None)
            clock = time.monotonic()
            sfm.match_features(workspace, matching, options=options, tick=tick)
            timings["matching"] = time.monotonic() - clock
            progress.update(task, total=1, completed=1)
            stages["matched"] = [*stages["matched"], matching]
            stages["mapped"] = False  # new matches: map again
            workspace.write_stages(stages)

        if stages["mapped"] == mapper and workspace.sparse.is_dir():
            _done(progress, f"mapping ({mapper}): done earlier")
            reconstruction = sfm.load_model(workspace)
        else:
            counted = mapper == "incremental"  # the only mapper that reports each photo it registers
            what = f"mapping ({mapper}{', photos registered' if counted else ''})"
            _, advance, tick = _stage(progress, what, len(photos.names) if counted else None)
            clock = time.monotonic()
            reconstruction = sfm.map_photos(workspace, photos, mapper=mapper, options=options, on_image=advance,
                                            tick=tick)
            timings["mapping"] = time.monotonic() - clock
            stages["mapped"] = mapper
            workspace.write_stages(stages)

        model = sfm.to_sparse_model(reconstruction)
        gps = photos.gps_by_name()
        frame = align.capture_frame(model.names, model.camera_to_world, gps, gps_origin_from=list(gps.values()) or None)
        _, advance, _ = _stage(progress, "writing the scene", len(model.names))
        clock = time.monotonic()
        transforms = scene.write_scene(
            args.output, photos.folder, names=model.names, camera_to_world_cv=model.camera_to_world, image_ids=model.image_ids,
            intrinsics=model.intrinsics, points=model.points, colours=model.colours, frame=frame, workers=workers, advance=advance,
        )
        timings["writing"] = time.monotonic() - clock
    _report(photos, model, frame, mapper=mapper, others=sfm.other_models(workspace), transforms=transforms,
            seconds=time.monotonic() - started, timings=timings)
    return 0


def left_out(photos: PhotoSet, registered: List[str]) -> List[Tuple[str, str]]:
    """(name, why) of every photo of the folder not in the scene, sorted by name: "cannot be read" (it
    does not decode) or "not registered" (structure-from-motion did not place it)."""
    placed = set(registered)
    out = [(name, "cannot be read") for name, _ in photos.unreadable]
    out += [(name, "not registered") for name in photos.names if name not in placed]
    return sorted(out)


def _cameras_line(photos: PhotoSet, model) -> str:
    """E.g. ``2 cameras: 320x240 px, courtyard: fl_x 256.1, fl_y 256.0 px (16 photos); ...``: each
    registered camera's intrinsics, described by its photos' size and EXIF camera."""
    camera_of = photos.camera_of()
    seen: Dict[int, List[str]] = {}
    for name, camera_id in zip(model.names, model.camera_ids):
        seen.setdefault(camera_id, []).append(name)
    parts = []
    for camera_id, names in seen.items():
        values = model.intrinsics[model.names.index(names[0])]
        parts.append(f"{camera_of[names[0]].describe()}: fl_x {values['fl_x']:.1f}, fl_y {values['fl_y']:.1f} px "
                     f"({len(names)} photo{'s' if len(names) != 1 else ''})")
    return f"{len(parts)} camera{'s' if len(parts) != 1 else ''}: " + "; ".join(parts)


def _report(photos: PhotoSet, model, frame: align.CaptureFrame, *, mapper: str, others: List[int], transforms: Path,
            seconds: float, timings: dict) -> None:
    total = photos.num_in_folder
    share = 100.0 * len(model.names) / total
    print(f"registered {len(model.names)} of {total} photos ({share:.1f} %) by {mapper} mapping, mean reprojection "
          f"error {model.mean_reprojection_error:.3f} px, {len(model.points)} sparse points, {seconds / 60:.1f} min")
    print(_cameras_line(photos, model))
    print(f"frame: {frame.describe()}")
    missing = left_out(photos, model.names)
    if missing:
        print(f"left out {len(missing)} of {total} photos: " + ", ".join(f"{name} ({why})" for name, why in missing))
    if others:
        print(f"({len(others)} smaller separate reconstruction(s) of {', '.join(map(str, others))} photos were left out)")
    print(f"wrote {transforms} (" + ", ".join(f"{name} {value:.0f} s" for name, value in timings.items()) + ")")


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if sfm is None:
        print(f"{PROG}: error: {_missing_pycolmap()}", file=sys.stderr)
        return 1
    try:
        return run(args, Console(stderr=True))
    except ProcessDataError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 1
    except OSError as error:  # an unwritable --output, a full disk: nothing half-written is published
        print(f"{PROG}: error: {error.strerror or error} ({error.filename or args.output}); the scene was not written", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


def entrypoint() -> None:
    """Console script."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
