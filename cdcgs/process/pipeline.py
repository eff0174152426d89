"""Structure from motion with pycolmap: photos or a video in, a scene for ``cdcgs train`` out.

Stages, each timed and shown with a progress bar:

1. images: photos copied upright (EXIF orientation), or the sharpest frame of each window of a
   video, into ``SCENE/input``;
2. features: SIFT (on the GPU where pycolmap was built with CUDA), one shared camera by default
   (``SIMPLE_RADIAL``, COLMAP's default: one focal length, which the incremental mapper's first
   bundle adjustments cannot pull apart as they did OPENCV's on bonsai), into
   ``SCENE/distorted/database.db``;
3. matching: exhaustive for photo sets up to ``exhaustive_limit``, sequential for video frames,
   spatial for large sets with GPS in their EXIF, vocabulary tree with a tree file; or as asked;
4. mapping: incremental (or global) into ``SCENE/distorted/sparse/<k>``; the model with the
   most registered images is kept, the others are reported;
5. undistortion to PINHOLE images: ``SCENE/images`` and ``SCENE/sparse/0``;
6. ``SCENE/images_2``, ``_4``, ``_8``: the undistorted images downscaled.

The summary (images registered of total, points, mean reprojection error, time per stage, why
each unregistered image failed, and the jumps in the camera path that mark a model in pieces:
:func:`cdcgs.process.checks.path_jumps`) is returned and written to ``SCENE/process.json``.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

from ..errors import InputError, OptionError
from .checks import path_jumps
from .inputs import VIDEO_EXTENSIONS, copy_photos, list_photos, video_frames

__all__ = ["CAMERA_MODELS", "INIT_MIN_TRI_ANGLE", "MAPPERS", "MATCHERS", "ProcessOptions", "process"]

MATCHERS = ("auto", "exhaustive", "sequential", "spatial", "vocabtree")
MAPPERS = ("incremental", "global")
INIT_MIN_TRI_ANGLE = 8.0  # the incremental mapper's default first-pair angle (COLMAP's is 16)
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL", "OPENCV_FISHEYE", "FULL_OPENCV")
# What process writes into SCENE (and replaces with overwrite).
OUTPUTS = ("input", "distorted", "images", "images_2", "images_4", "images_8", "sparse", "stereo", "process.json")
MIN_FEATURES = 100  # an image with fewer SIFT features is reported as featureless
# Undistortion resamples every photo (bilinear), and COLMAP's undistorter also moves the principal
# point to the new image's centre: with almost no distortion that is a shift by half a pixel, a 2 x 2
# blur of every photo. Where no camera's distortion moves any pixel by more than this, the photos
# are kept as they are, with each camera's pinhole part.
KEEP_PHOTOS_BELOW_PX = 0.1


@dataclass(kw_only=True)
class ProcessOptions:
    """How ``cdcgs process`` runs (each field is a flag of the command)."""

    frames: int = 150  # frames kept from a video
    matcher: str = "auto"
    vocab_tree: str | None = None  # a COLMAP vocabulary tree file, for matcher vocabtree
    exhaustive_limit: int = 300  # auto: exhaustive matching up to this many photos
    overlap: int = 20  # sequential matching: each frame against the next this many (and quadratic steps)
    # One focal length and one radial term (COLMAP's default). OPENCV (INRIA's convert.py) has two
    # focal lengths: on bonsai they drifted apart from one of two clean first pairs and the model
    # broke (docs/process.md); SIMPLE_RADIAL kept it whole from both.
    camera_model: str = "SIMPLE_RADIAL"
    per_image_camera: bool = False  # one camera per image instead of one shared camera
    mapper: str = "incremental"
    calibrate_view_graph: bool = False  # global mapper: focal lengths from the view graph first
    # Incremental mapper: the smallest triangulation angle of its first pair, in degrees (None:
    # 8 for the incremental mapper). COLMAP's 16 made it start bonsai from a wide pair with many
    # wrong matches and the model broke, with OPENCV, PINHOLE and SIMPLE_RADIAL cameras alike; at 8
    # SIMPLE_RADIAL kept it whole (docs/process.md).
    init_min_tri_angle: float | None = None
    max_image_size: int = 3200  # SIFT works on images at most this large (longer side)
    max_features: int = 8192
    device: str = "auto"  # auto, cpu, cuda (features and matching)
    min_registered: float = 0.5  # fail when a smaller share of the images registers
    downscales: tuple = field(default=(2, 4, 8))
    seed: int = 0  # the mappers' random seed (with several threads the result still varies slightly)
    threads: int = 0  # CPU threads of extraction, matching and mapping; 0: all cores, 1: reproducible
    overwrite: bool = False
    progress: bool = True

    def __post_init__(self):
        checks = (
            (self.matcher in MATCHERS, f"--matcher must be one of {', '.join(MATCHERS)}, got {self.matcher!r}"),
            (self.mapper in MAPPERS, f"--mapper must be one of {', '.join(MAPPERS)}, got {self.mapper!r}"),
            (
                self.camera_model in CAMERA_MODELS,
                f"--camera-model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}",
            ),
            (self.device in ("auto", "cpu", "cuda"), f"--device must be auto, cpu or cuda, got {self.device!r}"),
            (self.threads >= 0, f"--threads must be 0 (all cores) or more, got {self.threads}"),
            (self.frames >= 3, f"--frames must be at least 3, got {self.frames}"),
            (
                self.init_min_tri_angle is None or 0.0 < self.init_min_tri_angle < 90.0,
                f"--init-min-tri-angle must be in (0, 90) degrees, got {self.init_min_tri_angle}",
            ),
            (self.overlap >= 1, f"--overlap must be at least 1, got {self.overlap}"),
            (0.0 <= self.min_registered <= 1.0, f"--min-registered must be in [0, 1], got {self.min_registered}"),
            (self.max_image_size >= 100, f"--max-image-size must be at least 100, got {self.max_image_size}"),
            (self.max_features >= 100, f"--max-features must be at least 100, got {self.max_features}"),
            (all(f >= 2 for f in self.downscales), f"downscales must be factors >= 2, got {self.downscales}"),
        )
        for ok, message in checks:
            if not ok:
                raise OptionError(message)
        if self.matcher == "vocabtree" and not (self.vocab_tree and os.path.isfile(self.vocab_tree)):
            raise OptionError("--matcher vocabtree needs --vocab-tree FILE (a COLMAP vocabulary tree)")
        if self.calibrate_view_graph and self.mapper != "global":
            raise OptionError("--calibrate-view-graph calibrates for --mapper global only")
        if self.init_min_tri_angle is not None and self.mapper != "incremental":
            raise OptionError("--init-min-tri-angle is read by --mapper incremental only")
        if self.init_min_tri_angle is None and self.mapper == "incremental":
            self.init_min_tri_angle = INIT_MIN_TRI_ANGLE
        if self.vocab_tree and self.matcher != "vocabtree":
            raise OptionError("--vocab-tree is read by --matcher vocabtree only")


class _Stages:
    """Times the stages and shows one bar over them."""

    def __init__(self, names: list[str], progress: bool, report=None):
        from tqdm import tqdm

        self.seconds: dict[str, float] = {}
        self.report = report
        self.bar = tqdm(total=len(names), desc="process", unit="stage", disable=not progress)

    @contextmanager
    def stage(self, name: str):
        """Times the stage; with ``report``, its time goes there as it ends, so that a run cut
        short, or one logged without bars, still shows the stages it finished."""
        self.bar.set_description(name)
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 3)
        if self.report is not None:
            self.report(f"{name}: {self.seconds[name]:.1f} s")
        self.bar.update(1)

    def close(self):
        self.bar.close()


def _check_paths(input_path: str, out: str, overwrite: bool) -> str:
    """'video' or 'photos'; refuses a missing input, and an output that would lose anything."""
    if not os.path.exists(input_path):
        raise InputError(input_path, "does not exist")
    if os.path.isdir(input_path):
        kind = "photos"
    elif input_path.lower().endswith(VIDEO_EXTENSIONS):
        kind = "video"
    else:
        raise InputError(input_path, f"is neither a folder of images nor a video ({', '.join(VIDEO_EXTENSIONS)})")
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(out, "--out names a file, not a folder")
    real_input = os.path.realpath(input_path)
    for name in OUTPUTS:
        target = os.path.realpath(os.path.join(out, name))
        if real_input == target or real_input.startswith(target + os.sep):
            raise InputError(
                input_path, f"lies inside {os.path.join(out, name)}, which cdcgs process writes: choose another --out"
            )
    existing = [name for name in OUTPUTS if os.path.exists(os.path.join(out, name))]
    if existing and not overwrite:
        raise InputError(
            out, f"already holds {', '.join(existing)}; pass --overwrite to replace them, or another --out"
        )
    return kind


def _device(pycolmap, name: str):
    if name == "cuda" and not pycolmap.has_cuda:
        raise OptionError("--device cuda: this pycolmap was built without CUDA (use auto or cpu)")
    if name == "cpu" or not pycolmap.has_cuda:
        return pycolmap.Device.cpu, "cpu"
    return pycolmap.Device.cuda, "cuda"


def _has_gps(pycolmap, database: str) -> bool:
    db = pycolmap.Database.open(database)
    try:
        return db.num_pose_priors() > 0
    finally:
        db.close()


def _failure_reasons(pycolmap, database: str, registered: set[str], min_matches: int) -> dict[str, str]:
    """Why each image outside ``registered`` did not register, read from the database."""
    db = pycolmap.Database.open(database)
    try:
        images = {image.image_id: image.name for image in db.read_all_images()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        best = dict.fromkeys(images, 0)
        partners = dict.fromkeys(images, 0)
        for pair_id, count in zip(pair_ids, inliers):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            for image_id in (a, b):
                best[image_id] = max(best[image_id], count)
                partners[image_id] += count >= min_matches
        reasons = {}
        for image_id, name in images.items():
            if name in registered:
                continue
            features = db.num_keypoints_for_image(image_id)
            if features < MIN_FEATURES:
                reasons[name] = f"too few features ({features} SIFT keypoints)"
            elif partners[image_id] == 0:
                reasons[name] = f"no matches with another image (at most {best[image_id]} verified inliers)"
            else:
                reasons[name] = (
                    f"matched to {partners[image_id]} image(s) but not registered (too few 2D-3D correspondences, "
                    "or it belongs to a separate model)"
                )
        return reasons
    finally:
        db.close()


def _image_sizes(folder: str, names: list[str]) -> list[tuple[int, int]]:
    from PIL import Image

    sizes = []
    for name in names:
        with Image.open(os.path.join(folder, name)) as image:  # reads the header only
            sizes.append(image.size)
    return sizes


def _downscale(images_dir: str, out: str, factors, progress: bool) -> None:
    from PIL import Image
    from tqdm import tqdm

    names = sorted(os.listdir(images_dir))
    for factor in factors:
        target = os.path.join(out, f"images_{factor}")
        os.makedirs(target, exist_ok=True)
        for name in tqdm(names, desc=f"images_{factor}", unit="img", disable=not progress, leave=False):
            with Image.open(os.path.join(images_dir, name)) as image:
                size = (max(1, round(image.width / factor)), max(1, round(image.height / factor)))
                image.resize(size, Image.Resampling.LANCZOS).save(os.path.join(target, name), quality=95)


def process(input_path: str, out: str, options: ProcessOptions | None = None, report=None) -> dict:
    """Run structure from motion on ``input_path`` (a folder of images or a video) and write a
    COLMAP scene that ``cdcgs train --data out`` reads; returns the summary (also out/process.json).
    ``report``: called with a line (``"features: 81.3 s"``) as each stage ends (the command prints
    them above its bar); None: nothing is printed.

    Raises:
        InputError: a missing, unreadable or undecodable input, too few images, an output that
            already holds a scene (without ``overwrite``), or too few images registered (naming
            them and why).
        OptionError: a refused option.
    """
    from ..io._pycolmap import import_pycolmap

    options = options or ProcessOptions()
    input_path, out = os.fspath(input_path), os.fspath(out)
    kind = _check_paths(input_path, out, options.overwrite)
    pycolmap = import_pycolmap()
    device, device_name = _device(pycolmap, options.device)
    quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 2  # COLMAP's log: errors only
    # With overwrite, the earlier result moves aside and comes back if this run fails.
    created = not os.path.exists(out)
    backup = os.path.join(out, f".process-previous-{os.getpid()}")
    previous = [name for name in OUTPUTS if os.path.lexists(os.path.join(out, name))]
    if previous:
        os.makedirs(backup)
        for name in previous:
            os.replace(os.path.join(out, name), os.path.join(backup, name))
    try:
        summary = _process(pycolmap, input_path, out, kind, device, device_name, options, report)
    except BaseException:
        for name in OUTPUTS:
            path = os.path.join(out, name)
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path, ignore_errors=True)
            elif os.path.lexists(path):
                os.remove(path)
        for name in previous:
            os.replace(os.path.join(backup, name), os.path.join(out, name))
        if previous:
            os.rmdir(backup)
        if created and os.path.isdir(out) and not os.listdir(out):
            os.rmdir(out)  # a failed run leaves no empty folder behind
        raise
    finally:
        pycolmap.logging.minloglevel = quiet
        if previous and os.path.isdir(backup):
            shutil.rmtree(backup, ignore_errors=True)
    return summary


def _process(pycolmap, input_path, out, kind, device, device_name, options, report) -> dict:
    from ..train.outputs import write_json

    os.makedirs(out, exist_ok=True)
    input_dir = os.path.join(out, "input")
    distorted = os.path.join(out, "distorted")
    database = os.path.join(distorted, "database.db")
    stages = _Stages(
        ["images", "features", "matching", "mapping", "undistortion", "downscaling"], options.progress, report
    )
    try:
        with stages.stage("images"):
            if kind == "video":
                names = video_frames(input_path, input_dir, options.frames, options.progress)
            else:
                names = copy_photos(list_photos(input_path), input_dir, options.progress)
        if len(names) < 3:
            raise InputError(input_path, f"structure from motion needs at least 3 images, got {len(names)}")
        os.makedirs(distorted, exist_ok=True)
        with stages.stage("features"):
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = options.camera_model
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.max_image_size = options.max_image_size
            extraction.sift.max_num_features = options.max_features
            extraction.num_threads = _threads(options)
            # One shared camera; photos of several sizes (portrait and landscape) get one per size,
            # since COLMAP's single-camera mode skips every image of another size than the first.
            sizes = _image_sizes(input_dir, names)
            if options.per_image_camera:
                mode = pycolmap.CameraMode.PER_IMAGE
            else:
                mode = pycolmap.CameraMode.SINGLE if len(set(sizes)) == 1 else pycolmap.CameraMode.AUTO
            pycolmap.extract_features(
                database,
                input_dir,
                camera_mode=mode,
                reader_options=reader,
                extraction_options=extraction,
                device=device,
            )
        matcher = options.matcher
        if matcher == "spatial" and not _has_gps(pycolmap, database):
            raise OptionError("--matcher spatial needs GPS positions in the images' EXIF, and these have none")
        if matcher == "auto":
            if kind == "video":
                matcher = "sequential"
            elif len(names) <= options.exhaustive_limit:
                matcher = "exhaustive"
            elif _has_gps(pycolmap, database):
                matcher = "spatial"
            else:
                matcher = "exhaustive"  # no offline alternative without GPS or a vocabulary tree
        with stages.stage("matching"):
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = _threads(options)
            if matcher == "exhaustive":
                pycolmap.match_exhaustive(database, matching_options=matching, device=device)
            elif matcher == "sequential":
                pairing = pycolmap.SequentialPairingOptions()
                pairing.overlap = options.overlap
                pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=device)
            elif matcher == "spatial":
                pycolmap.match_spatial(database, matching_options=matching, device=device)
            else:
                pairing = pycolmap.VocabTreePairingOptions()
                pairing.vocab_tree_path = options.vocab_tree
                pycolmap.match_vocabtree(database, matching_options=matching, pairing_options=pairing, device=device)
        sparse_all = os.path.join(distorted, "sparse")
        os.makedirs(sparse_all, exist_ok=True)
        with stages.stage("mapping"):
            models = _map(pycolmap, database, input_dir, sparse_all, options, len(names))
        registered_by_model = sorted(
            ((rec.num_reg_images(), index) for index, rec in models.items()), key=lambda x: (-x[0], x[1])
        )
        best = models[registered_by_model[0][1]] if models else None
        registered = {image.name for image in best.images.values() if image.has_pose} if best else set()
        reasons = _failure_reasons(pycolmap, database, registered, 15)
        for name in names:
            if name not in registered and name not in reasons:
                reasons[name] = "skipped by COLMAP's image reader (unreadable or of an unexpected size)"
        needed = max(3, math.ceil(options.min_registered * len(names)))
        if len(registered) < needed:
            listed = "; ".join(f"{name}: {why}" for name, why in sorted(reasons.items())[:20])
            more = f" (and {len(reasons) - 20} more)" if len(reasons) > 20 else ""
            raise InputError(
                input_path,
                f"only {len(registered)} of {len(names)} images registered (at least {needed} needed, "
                f"--min-registered {options.min_registered}): {listed}{more}",
            )
        with stages.stage("undistortion"):
            # The mappers' folder numbers need not follow their return order: write the kept one.
            kept_dir = os.path.join(distorted, "kept")
            os.makedirs(kept_dir, exist_ok=True)
            best.write(kept_dir)
            model_dir = os.path.join(out, "sparse", "0")
            distortion = max(_distortion_px(camera) for camera in best.cameras.values())
            if distortion <= KEEP_PHOTOS_BELOW_PX:
                _keep_photos(pycolmap, pycolmap.Reconstruction(kept_dir), input_dir, out, model_dir)
            else:
                pycolmap.undistort_images(out, kept_dir, input_dir)
            os.makedirs(model_dir, exist_ok=True)
            for name in os.listdir(os.path.join(out, "sparse")):
                path = os.path.join(out, "sparse", name)
                if os.path.isfile(path):
                    shutil.move(path, os.path.join(model_dir, name))
            shutil.rmtree(os.path.join(out, "stereo"), ignore_errors=True)
            for name in os.listdir(out):
                if name.startswith("run-colmap-"):
                    os.remove(os.path.join(out, name))
        with stages.stage("downscaling"):
            _downscale(os.path.join(out, "images"), out, options.downscales, options.progress)
    finally:
        stages.close()
    posed = [image for image in best.images.values() if image.has_pose]
    path = path_jumps([image.name for image in posed], [image.projection_center() for image in posed])
    others = [
        {"model": index, "images": count, "points": models[index].num_points3D()}
        for count, index in registered_by_model[1:]
    ]
    summary = {
        "input": os.path.abspath(input_path),
        "kind": kind,
        "images": len(names),
        "registered": len(registered),
        "unregistered": [{"name": name, "reason": why} for name, why in sorted(reasons.items())],
        "points": best.num_points3D(),
        "mean_reprojection_error": best.compute_mean_reprojection_error(),
        "cameras": best.num_cameras(),
        "other_models": others,
        "path": path,
        "matcher": matcher,
        "mapper": options.mapper,
        "distortion_px": distortion,
        "photos_resampled": distortion > KEEP_PHOTOS_BELOW_PX,
        "device": device_name,
        "seconds": stages.seconds,
        "pycolmap": pycolmap.__version__,
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()},
    }
    write_json(os.path.join(out, "process.json"), summary)
    return summary


def _distortion_px(camera, grid: int = 33) -> float:
    """The most that ``camera``'s lens distortion moves a pixel, over a grid of ``grid`` x ``grid``
    points spanning the image (corners included): each point taken to the camera's undistorted
    coordinates and back through its pinhole part (focal lengths and principal point) alone. 0 for
    a camera without distortion."""
    import numpy as np

    u, v = np.meshgrid(np.linspace(0.0, camera.width, grid), np.linspace(0.0, camera.height, grid))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    normalized = np.asarray(camera.cam_from_img(pixels), dtype=np.float64)
    if not np.isfinite(normalized).all():  # a point the model cannot undistort: treat as distorted
        return float("inf")
    pinhole = normalized * [camera.focal_length_x, camera.focal_length_y] + [
        camera.principal_point_x,
        camera.principal_point_y,
    ]
    return float(np.abs(pinhole - pixels).max())


def _keep_photos(pycolmap, model, input_dir: str, out: str, model_dir: str) -> None:
    """The undistortion stage for cameras with no distortion worth resampling for
    (:data:`KEEP_PHOTOS_BELOW_PX`): the registered photos copied unchanged to ``out/images`` and the
    model written to ``model_dir`` with each camera's pinhole part (PINHOLE: fx, fy, cx, cy)."""
    for camera in model.cameras.values():
        params = [camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y]
        camera.model = pycolmap.CameraModelId.PINHOLE
        camera.params = params
        model.cameras[camera.camera_id] = camera
    images_dir = os.path.join(out, "images")
    for image in model.images.values():
        if image.has_pose:
            target = os.path.join(images_dir, image.name)
            os.makedirs(os.path.dirname(target), exist_ok=True)
            shutil.copyfile(os.path.join(input_dir, image.name), target)
    os.makedirs(model_dir, exist_ok=True)
    model.write(model_dir)


def _threads(options: ProcessOptions) -> int:
    """pycolmap's ``num_threads``: -1 for all cores."""
    return options.threads if options.threads > 0 else -1


def _map(pycolmap, database: str, image_dir: str, sparse_all: str, options: ProcessOptions, count: int) -> dict:
    """The models pycolmap's mapper builds (index -> Reconstruction), written under ``sparse_all``."""
    from tqdm import tqdm

    if options.mapper == "global":
        if options.calibrate_view_graph:
            # COLMAP's view_graph_calibrator: focal lengths from the pairs' fundamental matrices.
            # Off by default: on the process tests' rendered room it found 158-210 px for a true 256
            # (the distortion took up the rest, and the model came out turned by 180 degrees).
            calibration = pycolmap.ViewGraphCalibrationOptions()
            calibration.random_seed = options.seed
            pycolmap.calibrate_view_graph(database, calibration)
        pipeline = pycolmap.GlobalPipelineOptions()
        pipeline.random_seed = options.seed
        pipeline.num_threads = _threads(options)
        return pycolmap.global_mapping(database, image_dir, sparse_all, pipeline)
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.random_seed = options.seed
    pipeline.mapper.init_min_tri_angle = options.init_min_tri_angle
    pipeline.num_threads = _threads(options)
    bar = tqdm(total=count, desc="registered", unit="img", disable=not options.progress, leave=False)
    try:
        return pycolmap.incremental_mapping(
            database, image_dir, sparse_all, pipeline, next_image_callback=lambda: bar.update(1)
        )
    finally:
        bar.close()
