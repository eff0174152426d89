"""How much of a training step a CUDA graph would give back: the step's work for one view, run
as the trainer runs it and replayed as one captured CUDA graph, at chosen numbers of Gaussians.

    python benchmarks/graph_step.py --data SCENE --images images --gaussians 300000 1000000 \
        [--ply run/point_cloud.ply] [--at 20001] [--steps 200] [--out graph.json]

The trainer is set up as ``profile_step.py --sync-free`` sets it up (its model resampled to the
count, every training view's intersection count known, so that every render goes into slots and
nothing in the step reads the device). For one view the script times, per step:

- ``train_step``: the trainer's own step (the view order fixed to that view), plain;
- ``eager``: the graph's body run as Python, step by step: the render into slots, the note of its
  count, the fused loss, the backward pass, the guard's record and one FusedAdam launch whose
  tables (addresses, rates) were built once;
- ``graph``: the same body captured once under ``torch.cuda.graph`` (Warp told of the external
  capture) and replayed;
- ``kernels``: the GPU time of the eager body's kernels (CUDA events around a replay are the same
  kernels with no host in between: the replay's time is the floor a captured step reaches).

It checks that a replay does what the eager body does: from the same parameters and moments, one
eager step and one replay give the same image loss and parameters equal to float rounding (CUDA's
atomics order the blend's sums differently run to run).

This is the experiment that led to ``cdcgs train --cuda-graph`` (:mod:`cdcgs.train.graph`), kept
because it isolates one step: its rates are those of the first step and its view is fixed, where
the training's captured step reads both from the device.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import torch
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from profile_step import _annotation, prepared

from cdcgs.kernels.adam import adam_quads
from cdcgs.train.loss import fused_photometric_loss, mse_to_psnr
from cdcgs.train.optim import launch_adam


class StaticAdam:
    """FusedAdam's launch with its two tables on the device, filled from the host only when asked
    (``fill``): a captured launch reads them at replay. The rates are those of the optimizer's
    next step; the step counts are not advanced (an experiment: see the module's docstring)."""

    def __init__(self, optimizer: torch.optim.Optimizer, device: torch.device):
        self.optimizer = optimizer
        self.device = device
        self.params = [p for group in optimizer.param_groups for p in group["params"]]
        self.table = torch.zeros(len(self.params), 7, dtype=torch.int64, device=device)
        self.rates = torch.zeros(len(self.params), 8, dtype=torch.float32, device=device)
        self.threads = sum(adam_quads(p.numel()) for p in self.params)

    def fill(self, grads: list[torch.Tensor]) -> None:
        """The tables for the parameters with ``grads`` (one per parameter, in order)."""
        rows, rates, start = [], [], 0
        params = iter(zip(self.params, grads))
        for group in self.optimizer.param_groups:
            for _ in group["params"]:
                p, grad = next(params)
                state = self.optimizer.state[p]
                t = float(state["step"]) + 1.0
                beta1, beta2 = (float(b) for b in group["betas"])
                addresses = [x.data_ptr() for x in (p, grad, state["exp_avg"], state["exp_avg_sq"])]
                rows.append([*addresses, start, p.numel(), p.numel() // p.shape[0]])
                corrections = (1.0 - beta1**t, (1.0 - beta2**t) ** 0.5)
                rates.append(
                    [float(group["lr"]), beta1, beta2, 1.0 - beta1, 1.0 - beta2, float(group["eps"]), *corrections]
                )
                start += adam_quads(p.numel())
        self.table.copy_(torch.tensor(rows, dtype=torch.int64))
        self.rates.copy_(torch.tensor(rates, dtype=torch.float32))

    def step(self, halt: torch.Tensor) -> None:
        launch_adam(self.table, self.rates, self.threads, None, halt)


def step_of(trainer, view: int, adam: StaticAdam, losses: torch.Tensor):
    """The step's work for ``view``: everything a --sync-free step does on the device, nothing it
    reads back; ``run(fill)`` runs it (``fill``: build Adam's table from this call's gradients, the
    eager step's host work). ``losses[0]`` gets the image loss (for the check)."""
    lookahead = trainer.lookahead
    capacity = lookahead.capacity(view, trainer.model.num)
    if capacity is None:
        raise SystemExit(f"view {view} has no known count: the set-up renders every view first")
    photo = trainer.scene.train[view].image
    weight = trainer.config.ssim_weight
    step = trainer.step + 1

    def run(fill: bool):
        image, _, info = trainer._render(view, trainer.background, 1, capacity)
        lookahead.note(info, step, view, trainer.model.num)
        loss, mse = fused_photometric_loss(image, photo, weight)
        loss.backward()
        trainer.guard.record(loss, mse_to_psnr(mse), lookahead.halt)
        losses.copy_(loss.detach().reshape(1))
        if fill:
            adam.fill([p.grad for p in adam.params])
        adam.step(lookahead.halt)

    return run, capacity


def snapshot(trainer) -> list[torch.Tensor]:
    tensors = []
    for group in trainer.optimizer.param_groups:
        for p in group["params"]:
            state = trainer.optimizer.state[p]
            tensors += [p, state["exp_avg"], state["exp_avg_sq"]]
    return tensors


def timed(fn, steps: int) -> float:
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        fn()
    torch.cuda.synchronize()
    return (time.perf_counter() - start) * 1e3 / steps


def kernel_ms(fn, steps: int) -> float:
    """GPU time of ``fn``'s kernels per call (torch.profiler's CUDA rows, the labelled ranges and
    copies left out, as profile_step.py counts them)."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            fn()
        torch.cuda.synchronize()
    kernels = [
        e
        for e in prof.events()
        if e.device_type == DeviceType.CUDA and not _annotation(e) and not e.name.startswith("Memcpy")
    ]
    return sum(e.time_range.elapsed_us() for e in kernels) / 1e3 / steps


def measure(args, count: int) -> dict:
    with tempfile.TemporaryDirectory() as out:
        trainer = prepared(args, count, out)
        device = trainer.device
        view = args.view
        for _ in range(args.warmup):  # the trainer's own steps: kernels compiled, Adam's state made
            trainer.view_queue = [view]
            trainer.train_step()
        trainer._settle()
        trainer.view_queue = []

        def train_step():
            trainer.view_queue = [view]
            trainer.train_step()

        train_ms = timed(train_step, args.steps)
        trainer._settle()

        adam = StaticAdam(trainer.optimizer, device)
        losses = torch.zeros(1, device=device)
        run, capacity = step_of(trainer, view, adam, losses)
        params = adam.params

        def eager_step():
            run(True)
            trainer.optimizer.zero_grad(set_to_none=True)

        trainer.optimizer.zero_grad(set_to_none=True)
        for _ in range(3):
            eager_step()
        eager_ms = timed(eager_step, args.steps)
        kernels = kernel_ms(eager_step, min(args.steps, 50))

        # Capture, after the warm-up on a side stream that torch asks for.
        stream = torch.cuda.Stream(device)
        stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(stream):
            for _ in range(3):
                eager_step()
        torch.cuda.current_stream(device).wait_stream(stream)
        torch.cuda.synchronize()
        graph = torch.cuda.CUDAGraph()
        capture_start = time.perf_counter()
        with torch.cuda.graph(graph):
            wp_stream = wp.stream_from_torch(torch.cuda.current_stream(device))
            wp.capture_begin(stream=wp_stream, external=True)
            try:
                run(False)  # the gradients land in the graph's memory, which the table then names
            finally:
                wp.capture_end(stream=wp_stream)
        graph_grads = [p.grad for p in params]
        torch.cuda.synchronize()
        capture_ms = (time.perf_counter() - capture_start) * 1e3
        trainer.optimizer.zero_grad(set_to_none=True)

        # The check: one eager step and one replay from the same state.
        before = [t.clone() for t in snapshot(trainer)]
        eager_step()
        eager_loss = float(losses)
        eager_after = [t.clone() for t in snapshot(trainer)]
        with torch.no_grad():
            for t, b in zip(snapshot(trainer), before):
                t.copy_(b)
        adam.fill(graph_grads)
        graph.replay()
        torch.cuda.synchronize()
        graph_loss = float(losses)
        graph_after = snapshot(trainer)
        difference = max(float((a - b).abs().max()) for a, b in zip(eager_after, graph_after))
        moved = max(float((a - b).abs().max()) for a, b in zip(eager_after, before))

        graph_ms = timed(graph.replay, args.steps)
        halted = int(trainer.lookahead.halt[0])
        return {
            "gaussians": trainer.model.num,
            "view": view,
            "capacity": capacity,
            "train_step_ms": train_ms,
            "eager_ms": eager_ms,
            "graph_ms": graph_ms,
            "kernel_ms": kernels,
            "capture_ms": capture_ms,
            "check": {
                "eager_loss": eager_loss,
                "graph_loss": graph_loss,
                "largest_parameter_difference": difference,
                "largest_parameter_step": moved,
                "halted": halted,
            },
        }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="scene folder (COLMAP)")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--ply", default=None, help="a trained model to start from (else the scene's points)")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[300_000, 1_000_000])
    parser.add_argument("--view", type=int, default=0, help="the training view of every step")
    parser.add_argument("--at", type=int, default=20_001, help="iteration counter (after densification)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("graph_step.py measures CUDA graphs: it needs a CUDA GPU")
    args.strategy, args.reference_loss, args.torch_adam, args.sync_free = "3dgs", False, False, True
    rows = [measure(args, count) for count in args.gaussians]
    machine = torch.cuda.get_device_name()
    print(f"{machine}: ms per step (view {args.view})")
    print("gaussians  train_step  eager  graph  kernels  capture_ms  loss(eager/graph)  max|dparam|/max step")
    for r in rows:
        c = r["check"]
        print(
            f"{r['gaussians']:>9}  {r['train_step_ms']:10.3f}  {r['eager_ms']:5.3f}  {r['graph_ms']:5.3f}  "
            f"{r['kernel_ms']:7.3f}  {r['capture_ms']:10.1f}  {c['eager_loss']:.6f}/{c['graph_loss']:.6f}  "
            f"{c['largest_parameter_difference']:.2e}/{c['largest_parameter_step']:.2e} halted={c['halted']}"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine, "rows": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
