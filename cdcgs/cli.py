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

from .errors import InputError

log = logging.getLogger("cdcgs")


def _flag(name: str, prefix: str = "") -> str:
    return "--" + (prefix + name).replace("_", "-")


def _base_type(hint):
    """(python type, optional) of a field annotation such as ``int | None``."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if args:
        return args[0], True
    return hint, False


def _add_dataclass_options(parser, cls, prefix: str = "", skip=()):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        kind, optional = _base_type(hints[f.name])
        if dataclasses.is_dataclass(kind):
            sub_prefix = "" if f.name == "data" else f"{prefix}{f.name}_"
            _add_dataclass_options(parser, kind, sub_prefix)
            continue
        help_text = f.metadata.get("help", f.name.replace("_", " "))
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        dest = (prefix + f.name).replace("-", "_")
        if kind is bool:
            parser.add_argument(_flag(f.name, prefix), dest=dest, action=argparse.BooleanOptionalAction, default=default, help=f"{help_text} (default: {default})")
        else:
            parser.add_argument(_flag(f.name, prefix), dest=dest, type=kind, default=default, metavar=kind.__name__.upper(), help=f"{help_text} (default: {default})")


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


def _strategy_option_names() -> dict:
    from .train.strategy import registry

    names = {}
    for cls, _ in registry().values():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            names.setdefault(f.name, (hints[f.name], cls.__doc__ or ""))
    return names


def _add_train_parser(sub):
    from .train.config import TrainConfig

    p = sub.add_parser("train", help="train a scene", description="Train 3D Gaussians on a scene.", formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    _add_dataclass_options(p, TrainConfig)
    group = p.add_argument_group("strategy options", "override the chosen strategy's preset hyperparameters (default: the preset's)")
    for name, (hint, _) in sorted(_strategy_option_names().items()):
        kind, _ = _base_type(hint)
        if kind is bool:
            group.add_argument(_flag(name), dest=f"strategy__{name}", action=argparse.BooleanOptionalAction, default=None, help=f"strategy: {name.replace('_', ' ')}")
        else:
            group.add_argument(_flag(name), dest=f"strategy__{name}", type=kind, default=None, metavar=kind.__name__.upper(), help=f"strategy: {name.replace('_', ' ')}")
    p.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    from .train.config import TrainConfig
    from .train.trainer import Trainer, TrainingDiverged

    values = vars(args)
    if not values.get("data"):
        raise SystemExit("cdcgs train: --data DIR is required (a COLMAP folder or one with transforms.json)")
    config = _build_dataclass(TrainConfig, values)
    options = {k[len("strategy__") :]: v for k, v in values.items() if k.startswith("strategy__") and v is not None}
    if config.view:
        from .viewer import check_port_free

        check_port_free(config.view_host, config.view_port)  # before the scene loads, not after
    try:
        result = Trainer(config, options).run()
    except TrainingDiverged as err:
        print(f"cdcgs train: {err}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        return 130
    _print_result(config.out, result)
    return 0


def _print_result(out: str, result: dict) -> None:
    test = result["test"]
    if test.get("views"):
        lpips = f"{test['lpips']:.4f}" if test.get("lpips") is not None else "unavailable"
        print(f"test: PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f}, LPIPS {lpips} over {test['views']} views")
    print(f"{result['num_gaussians']} Gaussians, {result['train_seconds']:.1f} s training ({result['iterations_per_second']:.1f} it/s) on {result['device']}")
    print(f"outputs in {os.path.abspath(out)}")


def _load_run(out: str, device_name: str):
    """(config, scene, model) of a finished or interrupted run in ``out``."""
    from .io import load_checkpoint, load_scene, read_ply
    from .train.model import GaussianModel
    from .train.trainer import config_from_dict, resolve_device

    config_path = os.path.join(out, "config.json")
    if not os.path.isfile(config_path):
        raise InputError(out, "not a cdcgs output folder (no config.json)")
    with open(config_path) as f:
        config = config_from_dict(json.load(f)["train"])
    device = resolve_device(device_name)
    ply_path = os.path.join(out, "point_cloud.ply")
    if os.path.isfile(ply_path):
        model = GaussianModel.from_ply(read_ply(ply_path), device=device)
    else:
        model = GaussianModel.from_state_dict(load_checkpoint(os.path.join(out, "checkpoint.pt"))["model"], device=device)
        model.sh_degree = model.max_sh_degree
    d = config.data
    scene = load_scene(d.data, images=d.images, factor=d.factor, test_every=d.test_every, train_on_all=d.train_on_all, device=device, skip_missing=d.skip_missing)
    return config, scene, model


def cmd_eval(args) -> int:
    import torch

    from .train.evaluate import evaluate

    config, scene, model = _load_run(args.out_dir, args.device)
    background = torch.ones(3, device=model.device) if config.background == "white" else torch.zeros(3, device=model.device)
    metrics = evaluate(model, scene.test, background=background, antialiased=config.antialiased, save_dir=os.path.join(args.out_dir, "test_renders"))
    path = os.path.join(args.out_dir, "metrics.json")
    existing = json.load(open(path)) if os.path.isfile(path) else {}
    existing["test"] = {k: v for k, v in metrics.items() if k != "per_view"}
    existing["per_view"] = metrics.get("per_view", [])
    with open(path, "w") as f:
        json.dump(existing, f, indent=2)
    lpips = f"{metrics['lpips']:.4f}" if metrics.get("lpips") is not None else "unavailable"
    print(f"test: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, LPIPS {lpips}, {metrics['render_fps']:.1f} frames/s over {metrics['views']} views")
    print(f"written to {path} and {os.path.join(args.out_dir, 'test_renders')}")
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

    if args.video:
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ValueError("--video needs the imageio-ffmpeg package (pip install imageio-ffmpeg); without it, render PNGs") from None
    config, scene, model = _load_run(args.out_dir, args.device)
    background = torch.ones(3, device=model.device) if config.background == "white" else torch.zeros(3, device=model.device)
    if args.path == "orbit":
        reference = scene.train[0]
        cameras = [(f"orbit_{k:04d}", pose, reference.K, reference.width, reference.height) for k, pose in enumerate(orbit_path(scene.train, args.frames))]
    else:
        views = scene.test if args.path == "test" else scene.train
        cameras = [(os.path.splitext(v.name.replace(os.sep, "_"))[0], v.viewmat, v.K, v.width, v.height) for v in views]
    frames = []
    out_dir = args.out or os.path.join(args.out_dir, f"renders_{args.path}")
    if not args.video:
        os.makedirs(out_dir, exist_ok=True)
    from PIL import Image

    with torch.no_grad():
        for name, viewmat, K, width, height in cameras:
            image, _, _ = rasterize(**model.render_args(), viewmat=viewmat, K=K, width=width, height=height, background=background, antialiased=config.antialiased)
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

    if not os.path.isdir(args.out_dir):
        raise InputError(args.out_dir, "no such output folder")
    model = GaussianModel.from_state_dict(load_checkpoint(os.path.join(args.out_dir, "checkpoint.pt"))["model"])
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


def cmd_compare(args) -> int:
    from .train.trainer import plot_correlation

    histories = {}
    for out in args.out_dirs:
        try:
            history = json.load(open(os.path.join(out, "history.json")))
            config = json.load(open(os.path.join(out, "config.json")))
        except (OSError, ValueError) as err:
            raise InputError(out, f"not a finished cdcgs run ({err})") from None
        if not any("correlation" in e for e in history.get("strategy", [])):
            raise InputError(out, "the run logged no complexity-density correlation (train with a CDC strategy, or --log-correlation)")
        histories[f"{config['train']['strategy']} ({os.path.basename(os.path.normpath(out))})"] = history
    plot_correlation(histories, args.out)
    print(f"wrote {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cdcgs", description="3D Gaussian Splatting with CDC-GS densification on Warp kernels.")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_train_parser(sub)
    p = sub.add_parser("eval", help="evaluate a trained run on its test views")
    p.add_argument("out_dir", help="output folder of cdcgs train")
    p.add_argument("--device", default="auto", help="torch device (default: cuda when there is one)")
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
    p = sub.add_parser("view", help="look at a model in the browser (an output folder or any 3DGS PLY)",
                       description="Serve a browser viewer of a model: colour, depth, alpha and CDC-GS complexity, with the training cameras.")
    p.add_argument("path", help="output folder of cdcgs train, or a PLY in the 3DGS layout")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default: 8080; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1, this machine only; 0.0.0.0 lets other machines open it)")
    p.add_argument("--device", default="auto", help="torch device that renders (default: cuda when there is one)")
    p.add_argument("--max-fps", type=float, default=30.0, help="frames per second per browser, at most (default: 30)")
    p.add_argument("--max-height", type=int, default=None, help="frame height cap in pixels (default: 1080 on CUDA, 540 on the CPU)")
    p.set_defaults(func=cmd_view)
    p = sub.add_parser("compare", help="plot the complexity-density correlation of several runs (CDC-GS Fig. 4b)")
    p.add_argument("out_dirs", nargs="+", help="output folders of cdcgs train")
    p.add_argument("--out", default="correlation.png", help="PNG to write (default: correlation.png)")
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser("download", help="download a public dataset scene")
    p.add_argument("dataset", choices=["mipnerf360"], help="dataset")
    p.add_argument("--scene", required=True, help="scene name, e.g. garden")
    p.add_argument("--dest", default="data/360_v2", help="where the scene folder goes (default: data/360_v2)")
    p.add_argument("--url", default=None, help="archive URL (default: the official MipNeRF-360 archive)")
    p.add_argument("--delete-archive", action="store_true", help="delete the downloaded archive after extraction")
    p.set_defaults(func=cmd_download)
    return parser


def main(argv=None) -> int:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no Warp banner or module-load lines in the output
    logging.basicConfig(level=logging.WARNING, format="cdcgs: %(message)s")
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "frames", 1) is not None and getattr(args, "frames", 1) <= 0:
        parser.error("--frames must be positive")
    try:
        return args.func(args)
    except (InputError, ValueError) as err:
        print(f"cdcgs {args.command}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
