"""Structure-from-motion with pycolmap on the CPU: features, matching, mapping (incremental, global or
hierarchical).

Each camera of the capture (:meth:`PhotoSet.camera_groups`: make and model, image size, focal
length) gets its own COLMAP camera, so its own intrinsics. The work lives in ``SCENE/colmap``:
``database.db`` (features and matches), ``sparse/0`` (the largest reconstruction, COLMAP binary) and
``stages.json`` (which stages finished, with the options they ran with). A re-run skips the finished
stages and resumes an interrupted feature extraction where it stopped (COLMAP skips photos and pairs
already in the database); another ``--mapper`` maps again from the same matches.

This module imports pycolmap (the ``process`` extra); the rest of ``scalar_nerfstudio.process``
does not.
"""

from __future__ import annotations

import json
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple, TypeVar

import numpy as np
import pycolmap

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.process.errors import ProcessDataError
from scalar_nerfstudio.process.photos import PhotoSet

STAGES_VERSION = 2  # 2: one camera per group of photos (sizes and cameras may differ), the mapper recorded
MATCHING_METHODS = ("auto", "spatial", "sequential", "exhaustive")
#: ``--matching auto`` matches every pair up to this many photos (without GPS).
EXHAUSTIVE_MAX_PHOTOS = 50
MAPPERS = ("auto", "incremental", "global", "hierarchical")
#: ``--mapper auto`` maps this many photos or more globally, fewer incrementally. Incremental mapping
#: adds one photo at a time, each followed by bundle adjustment of the growing model, so its time grows
#: much faster than the number of photos (a 166-photo drone folder: 10 of its 18 minutes on 2 cores);
#: global mapping (GLOMAP) solves all rotations, then all positions, then one bundle adjustment, and
#: stays practical into the thousands, but leans harder on the matches being right. Below a few hundred
#: photos incremental mapping's time is affordable and its robustness is worth it.
GLOBAL_MIN_PHOTOS = 300
_CAMERA_MODEL = "OPENCV"  # fx, fy, cx, cy, k1, k2, p1, p2: what nerfstudio's OPENCV camera reads
_EXTRACT_CHUNK = 8  # photos per extraction call (the progress bar's step)
T = TypeVar("T")


@dataclass(frozen=True)
class SfmOptions:
    """How structure-from-motion runs."""

    max_image_size: int = 1000
    """Features are found on the photo resized so its long side is at most this many pixels."""
    matching: str = "auto"
    """Which pairs are matched: auto, spatial (GPS neighbours), sequential (by file name) or exhaustive."""
    spatial_neighbors: int = 20
    """spatial: each photo is matched with this many nearest photos by GPS position."""
    sequential_overlap: int = 10
    """sequential: each photo is matched with this many next photos by file name."""
    num_threads: int = -1
    """CPU threads COLMAP uses (-1: all cores)."""
    seed: int = 0
    """Random seed of the mapper's RANSAC and initial pair choice."""


class SparseModel(NamedTuple):
    """A reconstruction as plain arrays (COLMAP's world frame; OpenCV camera axes)."""

    names: List[str]
    """[N] file names of the registered photos, sorted."""
    camera_to_world: np.ndarray
    """[N, 4, 4] poses of the registered photos (OpenCV axes: x right, y down, z forward)."""
    image_ids: List[int]
    """[N] COLMAP image ids."""
    intrinsics: List[Dict[str, float]]
    """[N] w, h, fl_x, fl_y, cx, cy, k1, k2, p1, p2 of each registered photo's camera, full-resolution pixels."""
    camera_ids: List[int]
    """[N] COLMAP camera id of each registered photo (photos of one camera share its intrinsics)."""
    points: np.ndarray
    """[P, 3] sparse points."""
    colours: np.ndarray
    """[P, 3] uint8 point colours."""
    mean_reprojection_error: float
    """Mean reprojection error of the points' observations, pixels."""


def resolve_matching(method: str, photos: PhotoSet) -> str:
    """``auto`` -> spatial when every photo has GPS, exhaustive up to :data:`EXHAUSTIVE_MAX_PHOTOS`
    photos, else sequential. Raises :class:`ProcessDataError` for spatial without GPS."""
    if method not in MATCHING_METHODS:
        raise ProcessDataError(f"--matching {method!r}: choose one of {', '.join(MATCHING_METHODS)}")
    if method == "spatial" and not photos.all_have_gps:
        missing = photos.without_gps()
        raise ProcessDataError(
            f"--matching spatial pairs photos by their EXIF GPS positions, but {len(missing)} of {len(photos.photos)} "
            f"photo(s) have none (e.g. {', '.join(missing[:3])}); use --matching exhaustive (up to ~{EXHAUSTIVE_MAX_PHOTOS} "
            "photos) or sequential (photos taken in file-name order)"
        )
    if method != "auto":
        return method
    if photos.all_have_gps:
        return "spatial"
    return "exhaustive" if len(photos.photos) <= EXHAUSTIVE_MAX_PHOTOS else "sequential"


def resolve_mapper(method: str, num_photos: int) -> str:
    """``auto`` -> incremental below :data:`GLOBAL_MIN_PHOTOS` photos, else global; another name is kept.

    Raises:
        ProcessDataError: ``method`` is not one of :data:`MAPPERS`.
    """
    if method not in MAPPERS:
        raise ProcessDataError(f"--mapper {method!r}: choose one of {', '.join(MAPPERS)}")
    if method != "auto":
        return method
    return "incremental" if num_photos < GLOBAL_MIN_PHOTOS else "global"


class Workspace:
    """``SCENE/colmap`` and its ``stages.json``."""

    def __init__(self, colmap_dir: Path):
        self.dir = Path(colmap_dir)
        self.database = self.dir / "database.db"
        self.sparse = self.dir / "sparse" / "0"
        self.stages_path = self.dir / "stages.json"

    def read_stages(self) -> Optional[dict]:
        if not self.stages_path.exists():
            return None
        try:
            return json.loads(self.stages_path.read_text())
        except (OSError, ValueError) as error:
            raise ProcessDataError(f"{self.stages_path}: unreadable ({error}); pass --overwrite to start over") from None

    def write_stages(self, stages: dict) -> None:
        atomic_write_text(self.stages_path, json.dumps(stages, indent=2) + "\n")


def _signature(photos: PhotoSet, options: SfmOptions) -> dict:
    # The cameras as the database holds them: each group's size, photo count and first photo (its EXIF
    # labels left out, so the same photos without EXIF, grouped the same way, still resume).
    cameras = [[key.width, key.height, len(names), names[0]] for key, names in photos.camera_groups().items()]
    return {"version": STAGES_VERSION, "photos": photos.names, "cameras": cameras,
            "max_image_size": options.max_image_size, "camera_model": _CAMERA_MODEL}


def open_workspace(colmap_dir: Path, photos: PhotoSet, options: SfmOptions) -> tuple:
    """(Workspace, stages): a new workspace, or an existing one made for the same photos and options.

    Raises:
        ProcessDataError: the workspace holds another run's features.
    """
    workspace = Workspace(colmap_dir)
    signature = _signature(photos, options)
    stages = workspace.read_stages()
    if stages is not None:
        for key, value in signature.items():
            if stages.get(key) != value:
                what = {
                    "version": f"an older process-data (stages version {stages.get(key)!r}, now {value!r})",
                    "photos": "another set of photos", "cameras": "photos of other sizes or cameras",
                }.get(key, f"{key} {stages.get(key)!r} (now {value!r})")
                raise ProcessDataError(f"{workspace.dir} was made with {what}; pass --overwrite to start over")
        return workspace, stages
    workspace.dir.mkdir(parents=True, exist_ok=True)
    stages = {**signature, "extracted": False, "matched": [], "mapped": False}
    workspace.write_stages(stages)
    return workspace, stages


def _run_in_thread(function: Callable[[], T], tick: Optional[Callable[[], None]] = None) -> T:
    """Run a long pycolmap call (it releases the GIL) while ``tick`` keeps a spinner alive."""
    result: dict = {}

    def target() -> None:
        try:
            result["value"] = function()
        except BaseException as error:  # re-raised below, in the caller's thread
            result["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(0.2)
        if tick is not None:
            tick()
    if "error" in result:
        raise result["error"]
    return result["value"]  # the thread ended without an error: it set the value


def _image_cameras(workspace: Workspace) -> Tuple[Dict[str, int], set]:
    """(photo name -> COLMAP camera id of the photos in the database, names of those with keypoints)."""
    with pycolmap.Database.open(workspace.database) as database:
        images = database.read_all_images()
        with_keypoints = {image.name for image in images if database.exists_keypoints(image.image_id)}
        return {image.name: image.camera_id for image in images}, with_keypoints


def extract_features(workspace: Workspace, photos: PhotoSet, *, options: SfmOptions,
                     advance: Callable[[int], None]) -> None:
    """SIFT on every photo not yet in the database, :data:`_EXTRACT_CHUNK` photos of one camera per
    call. Each camera of :meth:`PhotoSet.camera_groups` gets one COLMAP camera (OPENCV, focal from its
    first photo's EXIF when it has one), created with its first photo and shared by the others.

    (pycolmap's ``CameraMode.AUTO`` compares a photo only with the one read before it, in one call, so
    interleaved sizes or chunked calls would give a camera per run of photos: the cameras are chosen
    here, with ``existing_camera_id``.)"""
    camera_of_photo, done = _image_cameras(workspace)
    todo = [name for name in photos.names if name not in done]
    advance(len(photos.names) - len(todo))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = options.max_image_size
    extraction.num_threads = options.num_threads
    for names in photos.camera_groups().values():
        camera_id = next((camera_of_photo[name] for name in names if name in camera_of_photo), -1)
        group_todo = [name for name in names if name not in done]
        for start in range(0, len(group_todo), _EXTRACT_CHUNK):
            chunk = group_todo[start : start + _EXTRACT_CHUNK]
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = _CAMERA_MODEL
            reader.existing_camera_id = camera_id
            pycolmap.extract_features(
                workspace.database, photos.folder, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
            )
            if camera_id < 0:
                camera_of_photo = _image_cameras(workspace)[0]
                camera_id = camera_of_photo[chunk[0]]
            advance(len(chunk))
    with pycolmap.Database.open(workspace.database) as database:
        images = {image.name: image.image_id for image in database.read_all_images()}
        empty = [name for name in photos.names if name not in images or database.num_keypoints_for_image(images[name]) == 0]
    if len(empty) == len(photos.names):
        raise ProcessDataError(f"{photos.folder}: no features found in any photo (blank or unreadable images?)")


def count_pairs(workspace: Workspace, matching: str, options: SfmOptions) -> int:
    """How many photo pairs ``matching`` will match."""
    with pycolmap.Database.open(workspace.database) as database:
        return len({tuple(sorted(pair)) for pair in _pair_generator(matching, options, database).all_pairs()})


def _pairing_options(matching: str, options: SfmOptions):
    if matching == "spatial":
        pairing = pycolmap.SpatialPairingOptions()
        pairing.max_num_neighbors = options.spatial_neighbors
        pairing.max_distance = 1e7  # metres: the neighbour count decides
        return pairing
    if matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        return pairing
    return pycolmap.ExhaustivePairingOptions()


def _pair_generator(matching: str, options: SfmOptions, database):
    generator = {"spatial": pycolmap.SpatialPairGenerator, "sequential": pycolmap.SequentialPairGenerator, "exhaustive": pycolmap.ExhaustivePairGenerator}[matching]
    return generator(_pairing_options(matching, options), database)


def match_features(workspace: Workspace, matching: str, *, options: SfmOptions, tick: Optional[Callable[[], None]] = None) -> None:
    """Match and geometrically verify the pairs of ``matching`` (pairs already matched are skipped)."""
    matcher = pycolmap.FeatureMatchingOptions()
    matcher.num_threads = options.num_threads
    function = {"spatial": pycolmap.match_spatial, "sequential": pycolmap.match_sequential, "exhaustive": pycolmap.match_exhaustive}[matching]
    _run_in_thread(
        lambda: function(workspace.database, matching_options=matcher, pairing_options=_pairing_options(matching, options), device=pycolmap.Device.cpu),
        tick,
    )


def verified_pairs(workspace: Workspace, min_inliers: int = 15) -> int:
    """Photo pairs whose matches passed geometric verification with at least ``min_inliers``."""
    with pycolmap.Database.open(workspace.database) as database:
        _, geometries = database.read_two_view_geometries()
    return sum(1 for geometry in geometries if len(geometry.inlier_matches) >= min_inliers)


def _mapping_call(mapper: str, workspace: Workspace, photos: PhotoSet, scratch: Path, *, options: SfmOptions,
                  on_image: Callable[[int], None]) -> Callable[[], Dict[int, pycolmap.Reconstruction]]:
    """The pycolmap call of ``mapper`` (incremental, global or hierarchical), CPU only, seeded."""
    if mapper == "incremental":
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = options.num_threads
        mapping.random_seed = options.seed
        return lambda: pycolmap.incremental_mapping(
            workspace.database, photos.folder, scratch, options=mapping, next_image_callback=lambda: on_image(1),
            initial_image_pair_callback=lambda: on_image(2),
        )
    if mapper == "global":
        glomap = pycolmap.GlobalPipelineOptions()
        glomap.num_threads = glomap.mapper.num_threads = options.num_threads
        glomap.random_seed = glomap.mapper.random_seed = options.seed
        glomap.mapper.global_positioning.use_gpu = False
        glomap.mapper.bundle_adjustment.ceres.use_gpu = False
        return lambda: pycolmap.global_mapping(workspace.database, photos.folder, scratch, options=glomap)
    if mapper == "hierarchical":
        clusters = pycolmap.HierarchicalPipelineOptions()
        clusters.num_threads = options.num_threads  # shared by its workers (incremental_options.num_threads is ignored)
        clusters.incremental_options.random_seed = options.seed
        return lambda: pycolmap.hierarchical_mapping(workspace.database, photos.folder, scratch, options=clusters)
    raise ProcessDataError(f"mapper {mapper!r}: choose one of {', '.join(MAPPERS[1:])}")


def map_photos(workspace: Workspace, photos: PhotoSet, *, mapper: str, options: SfmOptions,
               on_image: Callable[[int], None], tick: Optional[Callable[[], None]] = None) -> pycolmap.Reconstruction:
    """Map with ``mapper`` (incremental, global or hierarchical; ``on_image`` is called per photo
    registered by incremental mapping only); the largest reconstruction is written to ``sparse/0``.

    Raises:
        ProcessDataError: no reconstruction (the photos do not overlap enough).
    """
    scratch = workspace.dir / "sparse.partial"
    call = _mapping_call(mapper, workspace, photos, scratch, options=options, on_image=on_image)
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    try:
        models = _run_in_thread(call, tick)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    if not models:
        raise ProcessDataError(
            f"{photos.folder}: structure-from-motion ({mapper} mapping) could not place any photos: no pair of photos "
            f"shares enough matched features ({verified_pairs(workspace)} verified pair(s) with 15+ matches). The "
            "photos must overlap (about 60 % between neighbours); try --matching exhaustive or a larger "
            "--max-image-size"
        )
    best = max(models.values(), key=lambda model: model.num_reg_images())
    partial = workspace.sparse.with_name("0.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    best.write(partial)
    shutil.rmtree(workspace.sparse, ignore_errors=True)
    partial.rename(workspace.sparse)
    others = sorted((model.num_reg_images() for model in models.values() if model is not best), reverse=True)
    atomic_write_text(workspace.dir / "sparse" / "other_models.json", json.dumps(others) + "\n")
    return best


def load_model(workspace: Workspace) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(workspace.sparse)


def _intrinsics(camera: pycolmap.Camera) -> Dict[str, float]:
    """nerfstudio's intrinsics keys of an OPENCV camera."""
    fx, fy, cx, cy, k1, k2, p1, p2 = (float(v) for v in camera.params)
    return {"w": int(camera.width), "h": int(camera.height), "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
            "k1": k1, "k2": k2, "p1": p1, "p2": p2}


def to_sparse_model(reconstruction: pycolmap.Reconstruction) -> SparseModel:
    """Plain arrays of a reconstruction (one or more OPENCV cameras)."""
    cameras = reconstruction.cameras
    odd = sorted({camera.model_name for camera in cameras.values() if camera.model_name != _CAMERA_MODEL})
    if odd:
        raise ProcessDataError(f"expected {_CAMERA_MODEL} cameras in the reconstruction, got {', '.join(odd)}; "
                               "pass --overwrite to start over")
    registered = sorted((image.name, image_id) for image_id, image in reconstruction.images.items() if image.has_pose)
    camera_ids = [int(reconstruction.images[image_id].camera_id) for _, image_id in registered]
    intrinsics_of = {camera_id: _intrinsics(cameras[camera_id]) for camera_id in set(camera_ids)}
    poses = np.zeros((len(registered), 4, 4))
    for k, (_, image_id) in enumerate(registered):
        poses[k] = np.linalg.inv(np.vstack([reconstruction.images[image_id].cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]]))
    points = reconstruction.points3D
    xyz = np.array([p.xyz for p in points.values()], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points.values()], dtype=np.uint8).reshape(-1, 3)
    return SparseModel(
        names=[name for name, _ in registered],
        camera_to_world=poses,
        image_ids=[image_id for _, image_id in registered],
        intrinsics=[intrinsics_of[camera_id] for camera_id in camera_ids],
        camera_ids=camera_ids,
        points=xyz,
        colours=rgb,
        mean_reprojection_error=float(reconstruction.compute_mean_reprojection_error()),
    )


def other_models(workspace: Workspace) -> List[int]:
    path = workspace.dir / "sparse" / "other_models.json"
    try:
        return [int(v) for v in json.loads(path.read_text())]
    except (OSError, ValueError):
        return []


def quiet_colmap() -> None:
    """Keep COLMAP's INFO log off the terminal (warnings and errors still show)."""
    pycolmap.logging.minloglevel = 1


__all__ = [
    "EXHAUSTIVE_MAX_PHOTOS",
    "GLOBAL_MIN_PHOTOS",
    "MAPPERS",
    "MATCHING_METHODS",
    "SfmOptions",
    "SparseModel",
    "Workspace",
    "count_pairs",
    "extract_features",
    "load_model",
    "map_photos",
    "match_features",
    "open_workspace",
    "other_models",
    "quiet_colmap",
    "resolve_mapper",
    "resolve_matching",
    "to_sparse_model",
    "verified_pairs",
]
