"""The 3DGS training loop: data, model, optimizer, strategy, evaluation, outputs, resume."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import random
import time

import numpy as np
import torch

from ..errors import InputError
from ..io import capture_rng_state, load_checkpoint, load_scene, restore_rng_state, save_checkpoint, write_ply
from ..render import rasterize
from .config import TrainConfig
from .evaluate import evaluate
from .loss import photometric_loss, psnr
from .model import GaussianModel, make_optimizer, position_lr
from .strategy import StepContext, make_strategy

log = logging.getLogger("cdcgs")


class TrainingDiverged(RuntimeError):
    """The loss became NaN or infinite; the last good state was written to the checkpoint."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device {name!r} is not a torch device (cuda, cuda:0, cpu, auto)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for, but torch sees no CUDA GPU")
    if device.type not in ("cuda", "cpu"):
        raise ValueError(f"device {name!r}: cdcgs runs on cpu or cuda")
    return device


def config_to_dict(config) -> dict:
    return dataclasses.asdict(config)


def config_from_dict(data: dict) -> TrainConfig:
    from .config import DataConfig
    from .model import LearningRates

    data = dict(data)
    data["data"] = DataConfig(**data["data"])
    data["lr"] = LearningRates(**data["lr"])
    return TrainConfig(**data)


class Trainer:
    """Runs one training from a :class:`TrainConfig` (``run()``), or resumes it."""

    def __init__(self, config: TrainConfig, strategy_options: dict | None = None):
        self.config = config
        self.strategy_options = dict(strategy_options or {})
        self.device = resolve_device(config.device)
        self.out = config.out
        self.checkpoint_path = os.path.join(self.out, "checkpoint.pt")

    # ----------------------------------------------------------------------------- set-up

    def _setup(self):
        config = self.config
        if not config.resume and not config.overwrite:
            previous = [name for name in ("checkpoint.pt", "metrics.json", "point_cloud.ply") if os.path.isfile(os.path.join(self.out, name))]
            if previous:
                raise InputError(self.out, f"already holds a cdcgs run ({', '.join(previous)}); pass --resume to continue it, --overwrite to replace it, or choose another --out")
        os.makedirs(self.out, exist_ok=True)
        resume_state = None
        if config.resume:
            resume_state = load_checkpoint(self.checkpoint_path, map_location="cpu")
            saved = resume_state.get("config", {})
            if saved.get("data", {}).get("data") != config.data.data:
                raise InputError(self.checkpoint_path, f"the checkpoint was trained on {saved.get('data', {}).get('data')!r}, not {config.data.data!r}")
            self.strategy_options = resume_state.get("strategy_options", self.strategy_options)
        torch.manual_seed(config.seed)
        np.random.seed(config.seed)
        random.seed(config.seed)
        d = config.data
        self.scene = load_scene(
            d.data, images=d.images, factor=d.factor, test_every=d.test_every, train_on_all=d.train_on_all,
            device=self.device, skip_missing=d.skip_missing, progress=config.progress,
        )  # fmt: skip
        self.strategy = make_strategy(config.strategy, self.strategy_options)
        self.generator = torch.Generator(device=self.device).manual_seed(config.seed)
        self.view_generator = torch.Generator().manual_seed(config.seed + 1)
        if resume_state is None:
            self.model = GaussianModel.from_points(
                self.scene.points, self.scene.colors, max_sh_degree=config.sh_degree, init_opacity=config.init_opacity,
                scale_rule=config.scale_rule, device=self.device,
            )  # fmt: skip
            self.optimizer = make_optimizer(self.model, config.lr, self.scene.extent)
            self.strategy_state = self.strategy.initialize_state(self.model)
            self.step = 0
            self.view_queue: list[int] = []
            self.history = {"step": [], "loss": [], "psnr": [], "gaussians": [], "eval": [], "strategy": []}
            self.train_seconds = 0.0
        else:
            self.model = GaussianModel.from_state_dict(resume_state["model"], device=self.device)
            self.optimizer = make_optimizer(self.model, config.lr, self.scene.extent)
            self.optimizer.load_state_dict(resume_state["optimizer"])
            self.strategy_state = {k: v.to(self.device) if torch.is_tensor(v) else v for k, v in resume_state["strategy_state"].items()}
            self.step = resume_state["step"]
            self.view_queue = resume_state["view_queue"]
            self.history = resume_state["history"]
            self.train_seconds = resume_state["train_seconds"]
            restore_rng_state(resume_state["rng"])
            self.generator.set_state(resume_state["generator"])
            self.view_generator.set_state(resume_state["view_generator"])
        if config.background == "white":
            self.fixed_background = torch.ones(3, device=self.device)
        else:
            self.fixed_background = torch.zeros(3, device=self.device)
        with open(os.path.join(self.out, "config.json"), "w") as f:
            json.dump({"train": config_to_dict(config), "strategy": self.strategy.config(), "scene": self._scene_summary()}, f, indent=2)

    def _scene_summary(self) -> dict:
        s = self.scene
        return {
            "root": s.root, "source": s.source, "train_views": len(s.train), "test_views": len(s.test),
            "initial_points": int(s.points.shape[0]), "extent": s.extent, "notes": s.notes,
            "image_size": [s.train[0].width, s.train[0].height],
        }  # fmt: skip

    # ------------------------------------------------------------------------------ pieces

    def _next_view(self) -> int:
        """Views in a fresh random order each epoch (3DGS)."""
        if not self.view_queue:
            self.view_queue = torch.randperm(len(self.scene.train), generator=self.view_generator).tolist()
        return self.view_queue.pop()

    def _background(self) -> torch.Tensor:
        if self.config.background == "random":
            return torch.rand(3, device=self.device, generator=self.generator)
        return self.fixed_background

    def _render(self, view_index: int, background=None):
        view = self.scene.train[view_index]
        return rasterize(
            **self.model.render_args(), viewmat=view.viewmat, K=view.K, width=view.width, height=view.height,
            background=self.fixed_background if background is None else background, antialiased=self.config.antialiased,
        )  # fmt: skip

    def state_dict(self) -> dict:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "strategy_state": self.strategy_state,
            "strategy_options": self.strategy_options,
            "step": self.step,
            "view_queue": list(self.view_queue),
            "history": self.history,
            "train_seconds": self.train_seconds,
            "rng": capture_rng_state(),
            "generator": self.generator.get_state(),
            "view_generator": self.view_generator.get_state(),
            "config": config_to_dict(self.config),
        }

    def save(self, ply: bool = True) -> None:
        save_checkpoint(self.checkpoint_path, self.state_dict())
        if ply:
            write_ply(os.path.join(self.out, "point_cloud.ply"), self.model.to_ply())

    def _evaluate(self, final: bool) -> dict:
        save_dir = os.path.join(self.out, "test_renders") if (final and self.config.save_renders) else None
        metrics = evaluate(self.model, self.scene.test, background=self.fixed_background, antialiased=self.config.antialiased, save_dir=save_dir)
        summary = {k: metrics.get(k) for k in ("psnr", "ssim", "lpips", "num_gaussians")}
        self.history["eval"].append({"step": self.step, **summary})
        return metrics

    # -------------------------------------------------------------------------------- loop

    def train_step(self) -> tuple[float, float, dict]:
        config = self.config
        self.step += 1
        step = self.step
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = position_lr(step, config.iters, config.lr, self.scene.extent)
        if step % config.sh_every == 0 and self.model.sh_degree < self.model.max_sh_degree:
            self.model.sh_degree += 1
        view_index = self._next_view()
        view = self.scene.train[view_index]
        background = self._background()
        image, _, info = self._render(view_index, background)
        target = view.image.float() / 255.0
        loss = photometric_loss(image, target, config.ssim_weight)
        ctx = StepContext(
            step=step, total_steps=config.iters, model=self.model, optimizer=self.optimizer, info=info,
            view_index=view_index, extent=self.scene.extent, generator=self.generator,
            render=self._render, views=self.scene.train, out_dir=self.out,
        )  # fmt: skip
        self.strategy.before_backward(ctx, self.strategy_state)
        loss.backward()
        loss_value, psnr_value = torch.stack([loss.detach(), psnr(image.detach(), target)]).tolist()
        if not math.isfinite(loss_value):
            self.step -= 1
            self.optimizer.zero_grad(set_to_none=True)
            save_checkpoint(self.checkpoint_path, self.state_dict())
            raise TrainingDiverged(
                f"the loss became {loss_value} at iteration {step}; training stopped before the optimizer step. "
                f"The last good state (iteration {self.step}) is in {self.checkpoint_path}"
            )
        strategy_log = self.strategy.after_backward(ctx, self.strategy_state)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        return loss_value, psnr_value, strategy_log

    def run(self) -> dict:
        """Train to ``config.iters`` (from the checkpoint with ``resume``), evaluate, write outputs."""
        self._setup()
        config = self.config
        from tqdm import tqdm

        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        viewer = self._open_viewer()
        bar = tqdm(total=config.iters, initial=self.step, disable=not config.progress, unit="it", dynamic_ncols=True)
        smoothed_loss = smoothed_psnr = None
        try:
            while self.step < config.iters:
                start = time.perf_counter()
                loss_value, psnr_value, strategy_log = self.train_step()
                self.train_seconds += time.perf_counter() - start
                if viewer is not None:
                    viewer.offer(self.model, self.step)
                smoothed_loss = loss_value if smoothed_loss is None else 0.9 * smoothed_loss + 0.1 * loss_value
                smoothed_psnr = psnr_value if smoothed_psnr is None else 0.9 * smoothed_psnr + 0.1 * psnr_value
                if strategy_log:
                    self.history["strategy"].append({"step": self.step, **strategy_log})
                if self.step % config.log_every == 0 or self.step == config.iters:
                    for key, value in (("step", self.step), ("loss", smoothed_loss), ("psnr", smoothed_psnr), ("gaussians", self.model.num)):
                        self.history[key].append(value)
                if self.step % 10 == 0 or self.step == config.iters:
                    bar.set_postfix(loss=f"{smoothed_loss:.4f}", psnr=f"{smoothed_psnr:.2f}", gaussians=self.model.num, refresh=False)
                bar.update(1)
                if not config.progress and (self.step % 1000 == 0 or self.step == config.iters):
                    print(
                        f"[{self.step}/{config.iters}] loss {smoothed_loss:.4f}, PSNR {smoothed_psnr:.2f} dB, "
                        f"{self.model.num} Gaussians, {self.step / max(self.train_seconds, 1e-9):.1f} it/s",
                        flush=True,
                    )
                if config.eval_every and self.step % config.eval_every == 0 and self.step < config.iters and self.scene.test:
                    metrics = self._evaluate(final=False)
                    bar.write(f"[{self.step}] test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {self.model.num} Gaussians")
                if config.checkpoint_every and self.step % config.checkpoint_every == 0 and self.step < config.iters:
                    self.save(ply=False)
        except KeyboardInterrupt:
            bar.close()
            self.save()
            print(f"interrupted at iteration {self.step}: checkpoint and PLY written to {self.out} (continue with --resume)")
            raise
        finally:
            if viewer is not None:
                viewer.stop()
        bar.close()
        return self.finish()

    def _open_viewer(self):
        """The browser viewer of ``--view``, started, or None."""
        if not self.config.view:
            return None
        from ..viewer import ViewerSettings, training_viewer

        return training_viewer(self, ViewerSettings(host=self.config.view_host, port=self.config.view_port, max_fps=10.0))

    def finish(self) -> dict:
        self.save()
        metrics = self._evaluate(final=True) if self.scene.test else {"views": 0}
        peak = torch.cuda.max_memory_allocated(self.device) / 1e9 if self.device.type == "cuda" else None
        result = {
            "test": {k: v for k, v in metrics.items() if k != "per_view"},
            "per_view": metrics.get("per_view", []),
            "num_gaussians": self.model.num,
            "iterations": self.step,
            "train_seconds": self.train_seconds,
            "iterations_per_second": self.step / max(self.train_seconds, 1e-9),
            "peak_gpu_memory_gb": peak,
            "device": torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else "cpu",
            "strategy": self.strategy.config(),
        }
        with open(os.path.join(self.out, "metrics.json"), "w") as f:
            json.dump(result, f, indent=2)
        with open(os.path.join(self.out, "history.json"), "w") as f:
            json.dump(self.history, f)
        plot_curves(self.history, os.path.join(self.out, "curves.png"))
        if any("correlation" in entry for entry in self.history["strategy"]):
            plot_correlation({self.strategy.config()["name"] + f" ({self.config.strategy})": self.history}, os.path.join(self.out, "correlation.png"))
        return result


def correlation_curve(history: dict) -> tuple[list[int], list[float]]:
    points = [(e["step"], e["correlation"]) for e in history["strategy"] if "correlation" in e]
    return [p[0] for p in points], [p[1] for p in points]


def plot_correlation(histories: dict, path: str) -> None:
    """Pearson correlation of complexity and density at each densification step (CDC-GS Fig. 4b)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for label, history in histories.items():
        steps, values = correlation_curve(history)
        ax.plot(steps, values, label=label)
    ax.set(title="complexity-density correlation", xlabel="iteration", ylabel="Pearson r(Gamma, Psi)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_curves(history: dict, path: str) -> None:
    """Loss, PSNR (training, smoothed; test at each evaluation) and #Gaussians over iterations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    steps = history["step"]
    axes[0].plot(steps, history["loss"], color="tab:blue")
    axes[0].set(title="training loss", xlabel="iteration", yscale="log")
    axes[1].plot(steps, history["psnr"], color="tab:blue", label="train (smoothed)")
    if history["eval"]:
        axes[1].plot([e["step"] for e in history["eval"]], [e["psnr"] for e in history["eval"]], "o-", color="tab:red", label="test")
    axes[1].set(title="PSNR (dB)", xlabel="iteration")
    axes[1].legend()
    axes[2].plot(steps, history["gaussians"], color="tab:green")
    axes[2].set(title="Gaussians", xlabel="iteration")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
