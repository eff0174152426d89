"""The peer's full training run: gsplat 1.5.3 trained on cdcgs's data and protocol, measured like ours.

    python benchmarks/peers/gsplat_train.py --data ../shared/data/bonsai --out outputs/gsplat_bonsai
    python benchmarks/peers/gsplat_train.py --data ../shared/data/bonsai --out outputs/gsplat_mcmc_bonsai \
        --strategy mcmc --cap-max 901363
    python benchmarks/run.py --sections training --training-run outputs/bonsai_adc outputs/gsplat_bonsai

``--out`` gets ``metrics.json`` with the keys ``cdcgs train`` writes (those ``benchmarks/run.py``'s
training section reads, plus a ``protocol`` record) and ``point_cloud.ply``.

gsplat's (checked against the 1.5.3 wheel and its examples/simple_trainer.py):
- rendering: ``gsplat.rasterization`` with packed=False, classic mode, near 0.01, far 1e10, all 16
  SH coefficients and sh_degree = min(step // 1000, 3) for the 0-based step;
- densification (``--strategy default``): ``gsplat.DefaultStrategy()`` with its defaults;
  ``initialize_state(scene_scale)``, ``step_pre_backward`` before ``loss.backward()`` and
  ``step_post_backward(packed=False)`` after the optimizer step, with the 0-based step, as
  simple_trainer calls them;
- densification (``--strategy mcmc``, simple_trainer's ``mcmc`` config): see below;
- scene_scale: 1.1 x the largest distance of a camera centre from their mean, over all views
  (simple_trainer: Parser.scene_scale x 1.1);
- learning rates: means 1.6e-4 x scene_scale, decayed by 0.01^(1/iters) per step (ExponentialLR),
  scales 5e-3, quats 1e-3, opacities 5e-2, sh0 2.5e-3, shN 2.5e-3 / 20; one Adam per parameter,
  eps 1e-15, betas (0.9, 0.999) (batch size 1).

Ours, so that the two runs differ in renderer and densification only:
- the scene from ``cdcgs.io.load_scene``, as ``cdcgs train --data`` reads it (image folder and
  size, every 8th image by sorted name held out, uint8 images on the GPU, no world normalisation);
  the Gaussians from ``GaussianModel.from_points`` (exact 3-NN scales, identity rotations, opacity
  0.1, SH DC from the point colours, the rest 0; ``--strategy mcmc``: opacity 0.5, scales x 0.1);
- the loss 0.8 L1 + 0.2 (1 - SSIM, 11 px Gaussian window) as ``cdcgs train`` computes it: the
  fused kernels ``cdcgs.train.loss.fused_photometric_loss`` (``--loss kornia``: kornia's SSIM and
  torch's L1, what this harness used before issue 21; gsplat's own trainer fuses its SSIM too),
  black background, the view order of ``Trainer._next_view`` (a fresh randperm per epoch from
  Generator(seed + 1)), the seeds of ``Trainer._setup``, Adam fused on CUDA (``--adam default``:
  torch's default, foreach, as simple_trainer);
- timing as ``Trainer.run``: perf_counter around each whole step (schedule, render, loss,
  backward, the loss/PSNR read-back, strategy, optimizer), summed, no extra synchronisation;
  set-up, progress output and evaluation outside. Peak memory: reset after set-up, read after the
  final evaluation. Evaluation: ``cdcgs.train.evaluate.evaluate`` itself, given gsplat's render.

Where it differs from our trainer: the densification is gsplat's (the point), and so are its
place in the step (after the optimizer step; ours runs before it), its 0-based step, the SH and
learning-rate step convention (ours is one iteration ahead) and scene_scale over all cameras
(ours: the training cameras; 0.13% apart on bonsai). gsplat 1.5.3's DefaultStrategy never resets
opacities (``step % reset_every == 0 & step > 0`` chains to a comparison that is always false);
its own trainer runs that way, so this one does too. The initial rotations are ours (identity);
simple_trainer draws its quaternions with torch.rand. gsplat builds its CUDA extension (JIT) on
first use: that happens before the timed loop.

``--strategy mcmc`` is what simple_trainer's ``mcmc`` config changes (checked against gsplat
v1.5.3's strategy/mcmc.py and examples/simple_trainer.py), the rest as above:
- ``gsplat.MCMCStrategy(cap_max=--cap-max)`` (default 1,000,000, gsplat's and its mcmc benchmark
  script's), its other fields at their defaults: noise_lr 5e5, refine_start_iter 500,
  refine_stop_iter 25,000, refine_every 100, min_opacity 0.005 (simple_trainer sets verbose, which
  only prints). ``initialize_state()`` takes no scene scale; ``step_pre_backward`` is the base
  class's no-op, called as simple_trainer calls it; ``step_post_backward(lr=...)`` after the
  optimizer step relocates the dead Gaussians and grows by 5% (up to cap_max; it never removes
  any, so a cap below the initial count keeps that count) at steps 600, 700, ..., 24,900, and
  adds position noise at every step, scaled by ``lr``. ``lr`` is ``means_lr(step + 1)``:
  simple_trainer steps the means' ExponentialLR before the strategy and passes its
  ``get_last_lr()``, the rate of the next step. The refinement steps empty torch's CUDA cache,
  inside the timed step as in simple_trainer;
- renders with absgrad=False (simple_trainer takes absgrad from DefaultStrategy only), packed=False;
- the loss gets 0.01 mean(sigmoid(opacities)) + 0.01 mean(exp(scales)) over every Gaussian (and
  every scale axis), after ``step_pre_backward`` and before ``loss.backward()`` (opacity_reg and
  scale_reg; the default config has both 0); the reported loss includes them, as ours;
- initial Gaussians: simple_trainer's init_opa 0.5 and init_scale 0.1, i.e. opacity 0.5 and
  scales log(0.1 sqrt(mean of the squared distances to the 3 nearest points)) (scikit-learn's
  neighbours, no floor). Here: ``GaussianModel.from_points(init_opacity=0.5, scale_rule="3dgs",
  scale_factor=0.1)``, the same mean floored at 1e-7 from our exact KNN, which is how ``cdcgs train
  --strategy mcmc`` starts (``MCMC.training_defaults``; its opacity rate 0.05 is gsplat's too).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import random
import sys
import time
from types import SimpleNamespace

import numpy as np
import torch
import warp as wp
from tqdm import tqdm

wp.config.log_level = wp.LOG_WARNING  # before cdcgs initialises Warp: no banner

from cdcgs.errors import InputError
from cdcgs.io import GaussianPly, load_scene, scene_extent, write_ply
from cdcgs.train.evaluate import describe_metrics, evaluate
from cdcgs.train.loss import fused_photometric_loss, mse_to_psnr, photometric_loss, psnr
from cdcgs.train.model import GaussianModel

EXPECTED_VERSION = "1.5.3"
# simple_trainer's rates at batch size 1; the means' rate is x scene_scale and decays to 0.01x.
GSPLAT_LRS = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 2.5e-3 / 20}
MEANS_LR_END = 0.01
# gsplat's parameter -> the GaussianModel parameter it starts from (both pre-activation)
FROM_OURS = {
    "means": "means",
    "scales": "log_scales",
    "quats": "quats",
    "opacities": "opacity_logits",
    "sh0": "sh_dc",
    "shN": "sh_rest",
}
SH_EVERY, MAX_SH_DEGREE, SSIM_WEIGHT = 1000, 3, 0.2
MCMC_CAP_MAX = 1_000_000  # MCMCStrategy's default cap_max


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainerSettings:
    """What one config of simple_trainer sets besides the strategy's own fields."""

    strategy_class: str  # gsplat's strategy class
    init_opacity: float  # init_opa
    init_scale: float  # times the initial 3-NN scales
    opacity_reg: float  # loss weight of mean(sigmoid(opacities))
    scale_reg: float  # loss weight of mean(exp(scales))


SETTINGS = {  # simple_trainer's "default" and "mcmc" configs
    "default": TrainerSettings(
        strategy_class="DefaultStrategy", init_opacity=0.1, init_scale=1.0, opacity_reg=0.0, scale_reg=0.0
    ),
    "mcmc": TrainerSettings(
        strategy_class="MCMCStrategy", init_opacity=0.5, init_scale=0.1, opacity_reg=0.01, scale_reg=0.01
    ),
}


def means_lr(step: int, iters: int, scene_scale: float) -> float:
    """The means' rate at 0-based ``step``: 1.6e-4 x scene_scale at 0, 0.01x that at ``iters``."""
    return GSPLAT_LRS["means"] * scene_scale * MEANS_LR_END ** (step / iters)


def sh_degree_at(step: int) -> int:
    return min(step // SH_EVERY, MAX_SH_DEGREE)


def view_order(count: int, seed: int):
    """Training view indices in the order ``Trainer._next_view`` gives them (``next()`` each step)."""
    generator = torch.Generator().manual_seed(seed + 1)
    while True:
        yield from reversed(torch.randperm(count, generator=generator).tolist())


def regularization(params: dict, settings: TrainerSettings) -> torch.Tensor | None:
    """simple_trainer's regularisers: opacity_reg mean(sigmoid(opacities [N])) + scale_reg
    mean(exp(scales [N, 3])), or None where both weights are 0."""
    if settings.opacity_reg == 0 and settings.scale_reg == 0:
        return None
    opacity = torch.sigmoid(params["opacities"]).mean()
    return settings.opacity_reg * opacity + settings.scale_reg * torch.exp(params["scales"]).mean()


def load_gsplat() -> tuple[SimpleNamespace | None, list[str]]:
    """(gsplat's rasterization, strategies and version; []), or (None, why it cannot run here)."""
    problems, api = [], None
    try:
        import gsplat

        api = SimpleNamespace(
            rasterization=gsplat.rasterization,
            DefaultStrategy=gsplat.DefaultStrategy,
            MCMCStrategy=gsplat.MCMCStrategy,
        )
        api.version = getattr(gsplat, "__version__", "?")
    except ImportError as err:
        problems.append(f"gsplat is not importable ({err}); install gsplat=={EXPECTED_VERSION} into this environment")
    if not torch.cuda.is_available():
        problems.append("torch sees no CUDA device; gsplat's rasterizer runs on CUDA GPUs only")
    if problems:
        return None, problems
    try:  # gsplat builds (JIT) or loads its CUDA extension on first use: now, outside the timed loop
        from gsplat.cuda._backend import _C
    except (ImportError, OSError, RuntimeError) as err:
        return None, [f"gsplat's CUDA extension failed to build or load ({type(err).__name__}: {err})"]
    if _C is None:
        return None, ["gsplat's CUDA extension is unavailable: gsplat found no CUDA toolkit (nvcc) to build it"]
    return api, []


def make_renderer(rasterization, params: dict, absgrad: bool):
    """render(view, viewmat [1, 4, 4], K [1, 3, 3], sh_degree, background [3] or None)
    -> (image [H, W, 3], alpha [H, W, 1], gsplat's info dict), from the current ``params``."""

    def render(view, viewmat, K, sh_degree, background=None):
        colors, alphas, info = rasterization(
            means=params["means"],
            quats=params["quats"],
            scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]),
            colors=torch.cat([params["sh0"], params["shN"]], 1),
            viewmats=viewmat,
            Ks=K,
            width=view.width,
            height=view.height,
            near_plane=0.01,
            far_plane=1e10,
            sh_degree=sh_degree,
            packed=False,
            absgrad=absgrad,
            rasterize_mode="classic",
            backgrounds=None if background is None else background[None],
        )
        return colors[0], alphas[0], info

    return render


def evaluate_with(render, params: dict, views, sh_degree: int, device: torch.device) -> dict:
    """``cdcgs.train.evaluate.evaluate`` itself on ``views``, drawing them with ``render``."""
    cameras = {id(v): (v.viewmat[None].to(device), v.K[None].to(device)) for v in views}

    def render_view(_model, view, background, antialiased=False):
        return render(view, *cameras[id(view)], sh_degree, background)

    model = SimpleNamespace(device=device, num=params["means"].shape[0])
    return evaluate(model, views, background=torch.zeros(3, device=device), render=render_view)


def train(args, api: SimpleNamespace, device: torch.device) -> int:
    """Set up, train ``args.iters`` steps, evaluate and write ``metrics.json``; the exit status."""
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    random.seed(args.seed)
    scene = load_scene(args.data, images=args.images, test_views=args.test_views, device=device, progress=args.progress)
    scene_scale = scene_extent(scene.views)  # all cameras, as gsplat's Parser
    settings, mcmc = SETTINGS[args.strategy], args.strategy == "mcmc"
    model = GaussianModel.from_points(
        scene.points,
        scene.colors,
        max_sh_degree=MAX_SH_DEGREE,
        init_opacity=settings.init_opacity,
        scale_rule="3dgs",
        scale_factor=settings.init_scale,
        device=device,
    )
    params = {name: torch.nn.Parameter(model.params[ours].detach()) for name, ours in FROM_OURS.items()}
    fused = args.adam == "fused" and device.type == "cuda"
    lrs = {**GSPLAT_LRS, "means": GSPLAT_LRS["means"] * scene_scale}
    optimizers = {  # betas (0.9, 0.999), torch's default
        name: torch.optim.Adam(
            [{"params": [p], "lr": lrs[name], "name": name}], eps=1e-15, fused=True if fused else None
        )
        for name, p in params.items()
    }
    strategy = api.MCMCStrategy(cap_max=args.cap_max) if mcmc else api.DefaultStrategy()
    strategy.check_sanity(params, optimizers)
    # simple_trainer's branches: MCMCStrategy's state needs no scene scale, and it has no absgrad
    state = strategy.initialize_state() if mcmc else strategy.initialize_state(scene_scale=scene_scale)
    render = make_renderer(api.rasterization, params, absgrad=False if mcmc else strategy.absgrad)
    cameras = [(v.viewmat[None].to(device), v.K[None].to(device)) for v in scene.train]
    order = view_order(len(scene.train), args.seed)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    bar = tqdm(total=args.iters, disable=not args.progress, unit="it", dynamic_ncols=True)
    train_seconds, loss_avg, psnr_avg = 0.0, None, None
    for step in range(args.iters):
        start = time.perf_counter()
        for group in optimizers["means"].param_groups:
            group["lr"] = means_lr(step, args.iters, scene_scale)
        index = next(order)
        view = scene.train[index]
        image, _, info = render(view, *cameras[index], sh_degree_at(step))
        strategy.step_pre_backward(params=params, optimizers=optimizers, state=state, step=step, info=info)
        if args.loss == "fused":
            loss, mse = fused_photometric_loss(image, view.image, SSIM_WEIGHT)
            image_psnr = mse_to_psnr(mse)
        else:
            target = view.image.float() / 255.0
            loss = photometric_loss(image, target, SSIM_WEIGHT)
            image_psnr = psnr(image.detach(), target)
        regularizer = regularization(params, settings)
        if regularizer is not None:
            loss = loss + regularizer
        loss.backward()
        loss_value, psnr_value = torch.stack([loss.detach(), image_psnr]).tolist()
        if not math.isfinite(loss_value):
            bar.close()
            print(f"gsplat_train: the loss became {loss_value} at iteration {step + 1}; stopped", file=sys.stderr)
            return 3
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        # MCMCStrategy's noise takes the means' rate that simple_trainer's scheduler, stepped just
        # before this call, gives the next step
        extra = {"lr": means_lr(step + 1, args.iters, scene_scale)} if mcmc else {"packed": False}
        strategy.step_post_backward(params=params, optimizers=optimizers, state=state, step=step, info=info, **extra)
        train_seconds += time.perf_counter() - start
        loss_avg = loss_value if loss_avg is None else 0.9 * loss_avg + 0.1 * loss_value
        psnr_avg = psnr_value if psnr_avg is None else 0.9 * psnr_avg + 0.1 * psnr_value
        done, count = step + 1, params["means"].shape[0]
        if done % 10 == 0 or done == args.iters:
            bar.set_postfix(loss=f"{loss_avg:.4f}", psnr=f"{psnr_avg:.2f}", gaussians=count, refresh=False)
        bar.update(1)
        if not args.progress and (done % 1000 == 0 or done == args.iters):
            rate = done / max(train_seconds, 1e-9)
            print(
                f"[{done}/{args.iters}] loss {loss_avg:.4f}, PSNR {psnr_avg:.2f} dB, {count} Gaussians, {rate:.1f} it/s"
            )
    bar.close()
    sh = torch.cat([params["sh0"], params["shN"]], 1).detach()
    write_ply(
        os.path.join(args.out, "point_cloud.ply"),
        GaussianPly(
            means=params["means"].detach(),
            log_scales=params["scales"].detach(),
            quats=params["quats"].detach(),
            opacity_logits=params["opacities"].detach(),
            sh=sh,
        ),
    )
    cuda = device.type == "cuda"
    peak = torch.cuda.max_memory_allocated(device) / 1e9 if cuda else None  # training only, as cdcgs reports it
    metrics = {"views": 0}
    if scene.test:
        metrics = evaluate_with(render, params, scene.test, sh_degree_at(args.iters - 1), device)
    result = {
        "test": {k: v for k, v in metrics.items() if k != "per_view"},
        "per_view": metrics.get("per_view", []),
        "num_gaussians": params["means"].shape[0],
        "iterations": args.iters,
        "train_seconds": train_seconds,
        "iterations_per_second": args.iters / max(train_seconds, 1e-9),
        "peak_gpu_memory_gb": peak,
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "strategy": {"name": f"gsplat {api.version} {settings.strategy_class}", **dataclasses.asdict(strategy)},
        "protocol": {
            "data": os.path.abspath(args.data),
            "images": args.images,
            "seed": args.seed,
            "train_views": len(scene.train),
            "test_views": len(scene.test),
            "image_size": [scene.train[0].width, scene.train[0].height],
            "initial_points": int(scene.points.shape[0]),
            "scene_scale": scene_scale,
            "adam": "fused" if fused else "torch default",
            "loss": args.loss,
            "renderer": f"gsplat {api.version} rasterization(packed=False, rasterize_mode='classic')",
            "init_opacity": settings.init_opacity,
            "init_scale": settings.init_scale,
            "opacity_reg": settings.opacity_reg,
            "scale_reg": settings.scale_reg,
        },
    }
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        json.dump(result, f, indent=2)
    if metrics["views"]:
        print(f"test: {describe_metrics(metrics)}")
    rate = result["iterations_per_second"]
    print(
        f"{result['num_gaussians']} Gaussians, {train_seconds:.1f} s of training ({rate:.1f} it/s), {result['device']}"
    )
    print(f"metrics in {os.path.abspath(os.path.join(args.out, 'metrics.json'))}")
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add = parser.add_argument
    add("--data", required=True, help="scene folder, as cdcgs train --data (COLMAP or transforms.json)")
    add("--out", required=True, help="output folder: metrics.json and point_cloud.ply")
    add("--iters", type=int, default=30_000, help="training iterations")
    add("--images", default=None, help="COLMAP image folder, as cdcgs train --images (default: images/)")
    add(
        "--test-views",
        metavar="FILE",
        default=None,
        help="hold out the images named in FILE, as cdcgs train --test-views (default: every 8th by name)",
    )
    add("--seed", type=int, default=0, help="seed of every random draw, as cdcgs train --seed")
    add("--adam", choices=("fused", "default"), default="fused", help="fused as ours, or torch's default as gsplat's")
    add(
        "--loss", choices=("fused", "kornia"), default="fused", help="the loss kernels of cdcgs train, or kornia's SSIM"
    )
    add(
        "--strategy",
        choices=tuple(SETTINGS),
        default="default",
        help="gsplat's DefaultStrategy, or its MCMCStrategy with simple_trainer's mcmc settings",
    )
    add(
        "--cap-max",
        type=int,
        default=None,
        help=f"with --strategy mcmc: the most Gaussians, MCMCStrategy's cap_max (default {MCMC_CAP_MAX:,})",
    )
    add("--progress", action=argparse.BooleanOptionalAction, default=True, help="show a progress bar")
    add("--overwrite", action="store_true", help="replace a run already in --out")
    args = parser.parse_args(argv)
    if args.iters <= 0:
        parser.error(f"--iters must be positive, got {args.iters}")
    if args.cap_max is not None and args.strategy != "mcmc":
        parser.error(f"--cap-max is MCMCStrategy's cap_max: it needs --strategy mcmc (got --strategy {args.strategy})")
    if args.strategy == "mcmc" and args.cap_max is None:
        args.cap_max = MCMC_CAP_MAX
    if args.cap_max is not None and args.cap_max <= 0:
        parser.error(f"--cap-max must be positive, got {args.cap_max}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if not os.path.exists(args.data):
        print(f"gsplat_train: {args.data}: no such scene folder", file=sys.stderr)
        return 2
    if os.path.isfile(os.path.join(args.out, "metrics.json")) and not args.overwrite:
        print(f"gsplat_train: {args.out} already holds a run; pass --overwrite or another --out", file=sys.stderr)
        return 2
    api, problems = load_gsplat()
    if problems:
        print(
            "gsplat_train: cannot run the gsplat peer here:", *(f"  - {p}" for p in problems), sep="\n", file=sys.stderr
        )
        return 2
    if api.version != EXPECTED_VERSION:
        print(f"gsplat_train: warning: gsplat {api.version}; this harness was checked against {EXPECTED_VERSION}")
    os.makedirs(args.out, exist_ok=True)
    try:
        return train(args, api, torch.device("cuda"))
    except (InputError, ValueError) as err:
        print(f"gsplat_train: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
