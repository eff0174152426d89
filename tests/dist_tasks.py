"""Processes for the data-parallel tests: a launcher that starts N ranks of a task on the CPU with
gloo, as torchrun would (its environment variables), and the tasks they run.

Each task runs in a fresh process, returns a picklable result, and the launcher collects every
rank's result or error with its exit code and time; ``run_here`` runs a one-process reference in
the caller's process instead (it saves a process start on a 2-core machine). The processes are
forked from multiprocessing's fork server, which has imported torch, Warp and cdcgs once for the
whole session (``PRELOAD``): a spawned process spent about 3 s of a 2-core machine on those imports
before its task began, more than most tasks take. Each process still starts as a new one (its own
process group, Warp runtime and kernels, signal handlers and exit), with the caller's environment
and working directory of the moment it starts.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import socket
import time
import traceback


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# What the fork server imports before it forks any process: nothing here may initialise CUDA (torch
# and Warp initialise their devices at first use, in each process) or start a thread that a fork
# cannot survive (numpy's OpenBLAS starts its threads at import and handles a fork itself).
PRELOAD = ["torch", "torch.distributed", "torch._dynamo", "warp", "cdcgs.train", "cdcgs.train.shard_training"]
PRELOAD += ["matplotlib.pyplot"]


def _entry(task: str, rank: int, world: int, port: int, result_path: str, kwargs: dict, environment: dict) -> None:
    # the caller's environment now: the fork server's is that of the session's first launch
    # (multiprocessing passes the working directory and sys.path itself)
    os.environ.clear()
    os.environ.update(environment)
    os.environ.update(
        {
            "RANK": str(rank),
            "WORLD_SIZE": str(world),
            "LOCAL_RANK": str(rank),
            "LOCAL_WORLD_SIZE": str(world),
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
        }
    )
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    start = time.monotonic()
    try:
        out = {"result": globals()[task](rank=rank, world=world, **kwargs)}
    except BaseException as err:  # the test looks at what each rank raised
        out = {"error": type(err).__name__, "message": str(err), "traceback": traceback.format_exc()}
    out["seconds"] = time.monotonic() - start
    with open(result_path, "wb") as f:
        pickle.dump(out, f)


def run_ranks(task: str, world: int, tmp_path, timeout: float = 60.0, **kwargs) -> list[dict]:
    """Run ``task`` on ``world`` processes (ranks 0..world-1, gloo on the CPU); each rank's
    {"result" or "error", "message", "seconds", "exitcode"}, in rank order."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)  # read when the server starts: the first launch
    port = free_port()
    environment = dict(os.environ)
    paths = [os.path.join(str(tmp_path), f"rank{rank}_{task}_{port}.pkl") for rank in range(world)]
    processes = [
        context.Process(target=_entry, args=(task, rank, world, port, paths[rank], kwargs, environment))
        for rank in range(world)
    ]
    for p in processes:
        p.start()
    deadline = time.monotonic() + timeout
    for p in processes:
        p.join(max(deadline - time.monotonic(), 0.1))
    outs = []
    for p, path in zip(processes, paths):
        if p.is_alive():
            p.kill()
            p.join()
            outs.append({"error": "Timeout", "message": f"still running after {timeout} s", "exitcode": None})
            continue
        out = {"error": "NoResult", "message": "the process left no result"}
        if os.path.exists(path):
            with open(path, "rb") as f:
                out = pickle.load(f)
        out["exitcode"] = p.exitcode
        outs.append(out)
    return outs


def ok(outs: list[dict]) -> list:
    """Every rank's result, in rank order; a rank without one fails the test with its error."""
    for rank, out in enumerate(outs):
        assert "result" in out, f"rank {rank}: {out.get('error')}: {out.get('message')}\n{out.get('traceback', '')}"
    return [out["result"] for out in outs]


# --------------------------------------------------------------------------------------- tasks


def task_config(scene, out, **overrides):
    from cdcgs.train.config import DataConfig, TrainConfig

    values = dict(
        data=DataConfig(data=str(scene), test_every=3),
        out=str(out),
        iters=12,
        device="cpu",
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        sh_every=4,
        log_every=2,
        batch_size=2,
        dist_timeout=20.0,
    )
    values.update(overrides)
    return TrainConfig(**values)


# Densification at 4 and 8, an opacity reset at 8, growth from a low threshold: a short run that
# changes the set of Gaussians and draws random numbers. In the appended order: runs that agree to
# rounding (one process against several) may sort two Gaussians a step apart differently in Morton
# order (tests/test_strategy.py tests that order), and compared row by row they would part there.
SCHEDULE = {
    "densify_from": 2,
    "densify_every": 4,
    "densify_until": 10,
    "reset_every": 8,
    "grad_threshold": 1e-5,
    "gaussian_order": "appended",
}


def params_of(trainer) -> dict:
    return {name: p.detach().cpu().clone() for name, p in trainer.model.params.items()}


def first_step_gradients(
    rank, world, scene, out, batch_size=2, strategy="3dgs", device="cpu", backend="auto", sh_degree=None, **overrides
):
    """The gradients of the first step after the reduction, before the optimizer step (on the CPU);
    ``sh_degree``: the spherical harmonics' degree of that step (its schedule's otherwise), with
    random higher coefficients and half the Gaussians' colours clamped at 0."""
    import torch

    from cdcgs.train.trainer import Trainer

    config = task_config(
        scene, out, batch_size=batch_size, strategy=strategy, device=device, dist_backend=backend, **overrides
    )
    trainer = Trainer(config, dict(SCHEDULE))
    captured = {}
    real_step = None

    def spy(*args, **kwargs):  # what Adam steps: the gradients times its gradient_scale (1 / the batch)
        scale = kwargs.get("gradient_scale", 1.0)
        for group in trainer.optimizer.param_groups:
            captured[group["name"]] = (group["params"][0].grad * scale).detach().cpu()
        return real_step(*args, **kwargs)

    from cdcgs.train.distributed import Ranks

    trainer.ranks = Ranks.from_environment(trainer.device, backend)
    trainer._given_ranks = trainer.ranks
    os.makedirs(out, exist_ok=True)
    trainer._setup()
    if sh_degree is not None:
        trainer.model.sh_degree = sh_degree
        with torch.no_grad():  # the higher coefficients nonzero, and half the Gaussians' colours clamped at 0
            draws = torch.Generator().manual_seed(1)
            sh_rest = trainer.model.params["sh_rest"]
            sh_rest.copy_(0.3 * torch.randn(sh_rest.shape, generator=draws).to(sh_rest.device))
            trainer.model.params["sh_dc"][::2] -= 2.0
    real_step = trainer.optimizer.step
    trainer.optimizer.step = spy
    trainer.train_step()
    trainer.ranks.close()
    return captured


def run_here(task: str, **kwargs) -> dict:
    """``task`` as one process (rank 0 of 1) in this process, without the cost of starting one:
    {"result"} or {"error", "message", "traceback"}, as :func:`run_ranks` gives. Only for tasks
    that leave the process as they found it (``train`` restores what it patches; not with
    ``stop_at``, whose signal would reach the caller)."""
    if kwargs.get("stop_at") is not None:
        raise ValueError("run_here: a task that signals itself needs a process of its own (run_ranks)")
    try:
        return {"result": globals()[task](rank=0, world=1, **kwargs)}
    except Exception as err:
        return {"error": type(err).__name__, "message": str(err), "traceback": traceback.format_exc()}


def train(
    rank,
    world,
    scene,
    out,
    strategy="3dgs",
    options=None,
    stop_at=None,
    die_at=None,
    perturb_at=None,
    tight_slots=False,
    viewer_on_rank_0=False,
    **overrides,
):
    """A whole run; the parameters' checksums after every step, the final parameters, and the
    files each rank wrote. ``stop_at``: this rank sends itself SIGTERM after that iteration;
    ``die_at``: rank 1 exits at once there; ``perturb_at``: rank 1 changes a parameter there;
    ``tight_slots``: with --sync-free, slots of exactly the last count, so that renders of grown
    Gaussians overflow and the run goes back; ``viewer_on_rank_0``: the steps replayed by default on
    the CPU too (as on CUDA), and rank 0 alone given a callback that renders beside the training
    (as the viewer is), which refuses them there."""
    import torch

    from cdcgs.train import lookahead, outputs
    from cdcgs.train import trainer as trainer_module
    from cdcgs.train.distributed import _checksum
    from cdcgs.train.trainer import Trainer

    writes = []
    from cdcgs.train import shard_training

    writers = (
        (trainer_module, "save_checkpoint"),
        (trainer_module, "write_ply"),
        (outputs, "write_json"),
        (shard_training, "save_checkpoint"),
        (shard_training, "write_ply"),
    )
    patched = [(module, name, getattr(module, name)) for module, name in writers]
    ShardedTrainer = shard_training.ShardedTrainer
    patched += [(Trainer, "train_step", Trainer.train_step), (ShardedTrainer, "train_step", ShardedTrainer.train_step)]
    for module, name, real in patched[:-2]:

        def spy(*args, _real=real, _name=name, **kwargs):
            writes.append(_name)
            return _real(*args, **kwargs)

        setattr(module, name, spy)
    checksums, sent, flag_buffers = [], [], set()
    real_steps = {Trainer: Trainer.train_step, ShardedTrainer: ShardedTrainer.train_step}

    def step(self):
        result = real_steps[type(self)](self)
        checksums.append((self.step, _checksum(self.model.params)))
        flag_buffers.add(self._flags.data_ptr())
        if stop_at is not None and rank == world - 1 and self.step >= stop_at and not sent:
            sent.append(self.step)
            os.kill(os.getpid(), signal.SIGTERM)
        if die_at is not None and rank == 1 and self.step >= die_at:
            os._exit(17)
        if perturb_at is not None and rank == 1 and self.step == perturb_at:
            with torch.no_grad():
                self.model.params["means"][0, 0] += 1e-3
        return result

    Trainer.train_step = ShardedTrainer.train_step = step
    # (iteration, positions, the views' agreed costs or None) of every split of a step's views
    splits = []
    real_positions = Trainer.positions

    def positions(self, first, views):
        mine = real_positions(self, first, views)
        costs = None
        if self.lookahead is not None:
            scale = self._downscale(first)
            costs = [self.lookahead.capacity(v, self.model.num, scale, agreed=True) for v in views]
        splits.append((first, list(mine), costs))
        return mine

    patched.append((Trainer, "positions", real_positions))
    Trainer.positions = positions
    from cdcgs.train.distributed import Ranks

    released = []  # at the close of the process group: whether no replayed step's graph was left
    patched.append((Ranks, "close", Ranks.close))
    real_close = Ranks.close

    def close(self, *args, **kwargs):
        graphs = getattr(trainers[0], "graphs", None) if trainers else None
        released.append(graphs is None or graphs.key is None)
        return real_close(self, *args, **kwargs)

    Ranks.close = close
    trainers = []
    if tight_slots:
        patched += [(lookahead, "MARGIN", lookahead.MARGIN), (lookahead, "FLOOR", lookahead.FLOOR)]
        lookahead.MARGIN, lookahead.FLOOR = 1.0, 0
    callbacks = []
    if viewer_on_rank_0:
        real_refusal = trainer_module.graph_refusal
        patched.append((trainer_module, "graph_refusal", real_refusal))
        trainer_module.graph_refusal = lambda trainer, default=False: real_refusal(trainer)  # the CPU not refused
        if rank == 0:

            class Beside:  # what the viewer says of itself
                renders_beside_training = True

                def on_start(self, trainer):
                    pass

                def on_step(self, trainer):
                    pass

                def on_end(self, trainer):
                    pass

            callbacks.append(Beside())
    trainer = Trainer(
        task_config(scene, out, strategy=strategy, **overrides),
        dict(SCHEDULE if options is None else options),
        callbacks=callbacks,
    )
    trainers.append(trainer)
    try:
        result = trainer.run()
    except KeyboardInterrupt as stop:
        return {"stopped": str(stop), "step": trainer.step, "checksums": checksums, "writes": writes}
    finally:  # run_here calls this in the test's own process
        for module, name, real in patched:
            setattr(module, name, real)
    return {
        "checksums": checksums,
        "params": params_of(trainer),
        "writes": writes,
        "metrics": {k: result[k] for k in ("num_gaussians", "iterations", "processes", "batch_size")},
        "released_before_close": released,
        "flag_buffers": len(flag_buffers),
        "sync_free": result.get("sync_free"),
        "cuda_graph": result.get("cuda_graph"),
        "dist_balance": result.get("dist_balance"),
        "splits": splits,
        "test": result["test"],
        "events": list(trainer.history["strategy"]),
    }


def surroundings(rank, world, names):
    """What a rank finds around it: the values of the environment variables ``names``, its
    working directory, its rank's variables, and whether its process is new (no CUDA or Warp
    runtime initialised before the task)."""
    import warp._src.context as warp_context

    return {
        "environment": {name: os.environ.get(name) for name in names},
        "cwd": os.getcwd(),
        "rank": (os.environ["RANK"], os.environ["WORLD_SIZE"]),
        "pid": os.getpid(),
        "warp_runtime": warp_context.runtime is not None,
    }


def failing_setup(rank, world, scene, out):
    """Rank 1 cannot read its scene; rank 0 is fine."""
    from cdcgs.errors import InputError
    from cdcgs.train import trainer as trainer_module
    from cdcgs.train.trainer import Trainer

    if rank == 1:

        def broken(*args, **kwargs):
            raise InputError(str(scene), "unreadable on this rank (the test's fault)")

        trainer_module.load_scene = broken
    Trainer(task_config(scene, out), dict(SCHEDULE)).run()


def lpips_agreement(rank, world, scene, out):
    """A run whose rank 1 lacks the LPIPS-VGG weights (stand-in networks, the same on both ranks
    otherwise): the test metrics each rank returns."""
    import torch

    from cdcgs.train import trainer as trainer_module
    from cdcgs.train.evaluate import LpipsMetric
    from cdcgs.train.trainer import Trainer

    class MeanAbsolute(torch.nn.Module):  # a stand-in LPIPS: any image size, one score per image
        min_size = 1

        def forward(self, a, b):
            return (a - b).abs().mean(dim=(1, 2, 3))

    def metric(device):
        if rank == 0:
            return LpipsMetric(device, nets={"vgg": MeanAbsolute(), "alex": MeanAbsolute()})
        partial = LpipsMetric(device, nets={"alex": MeanAbsolute()})
        partial.note = "LPIPS-vgg: its weights are not in this machine's cache (test)"
        return partial

    real = trainer_module.lpips_metric
    trainer_module.lpips_metric = metric
    try:
        return Trainer(task_config(scene, out, iters=4), dict(SCHEDULE)).run()["test"]
    finally:
        trainer_module.lpips_metric = real


def sharded_render(
    rank,
    world,
    rows,
    seed=0,
    width=40,
    height=30,
    sh_degree=2,
    split=False,
    spoil=None,
    visible_only=False,
    backend="gloo",
    default_float64=False,
    capacity=None,
    record_order=False,
    anomaly=False,
):
    """rasterize_shard on this rank's slice of a random scene (``rows``: the slices' sizes), the
    view of camera ``rank`` of an orbit, and the backward pass of a fixed weighting of its image:
    (the image, the alpha, the intersection count, the slice's gradients); ``split``: the SH passed
    as ``sh`` (degree 0) and ``sh_rest``, the gradient of the two concatenated; ``spoil``: (rank,
    "shape" or "nan"): that rank passes a means tensor of the wrong shape, or a NaN in it;
    ``backend`` "nccl": on GPU ``rank`` (the results come back on the CPU); ``default_float64``:
    torch's default dtype float64 in this process (the scene float32 still); ``capacity``: slots
    for the view's pairs, nothing read back, ``info.check()`` after the backward pass;
    ``record_order``: "order" holds the backward pass's projection adjoints (the view's index) and
    its waits for the other processes' gradients ("wait"), in the order they ran; ``anomaly``: the
    backward pass under torch's anomaly detection."""
    import torch
    import torch.distributed as dist

    from cdcgs.render import _Project
    from cdcgs.train import shards
    from cdcgs.train.shards import rasterize_shard

    order = []
    if record_order:  # this process only: it is a process of its own
        adjoint, wait = _Project.backward, shards._Pending.wait

        def noted_adjoint(ctx, *grads):
            order.append(next(i for i, camera in enumerate(cameras) if camera is ctx.camera))
            return adjoint(ctx, *grads)

        def noted_wait(self):
            if self._works:
                order.append("wait")
            return wait(self)

        _Project.backward = staticmethod(noted_adjoint)
        shards._Pending.wait = noted_wait

    device = torch.device("cpu")
    if backend == "nccl":
        device = torch.device("cuda", rank)
        torch.cuda.set_device(device)
    dist.init_process_group(backend, rank=rank, world_size=world)
    try:
        scene, cameras, weights = sharded_scene(sum(rows), world, seed, width, height, sh_degree)
        if default_float64:
            torch.set_default_dtype(torch.float64)
        start = sum(rows[:rank])
        mine = [t[start : start + rows[rank]].to(device).clone().requires_grad_(True) for t in scene]
        if spoil is not None and spoil[0] == rank:
            if spoil[1] == "shape":
                mine[0] = mine[0][1:]
            else:
                mine[0] = mine[0].detach().clone()
                mine[0][0, 1] = float("nan")
        sh = {"sh": mine[4]}
        if split:
            sh = {"sh": mine[4][:, :1].detach().clone().requires_grad_(True)}
            sh["sh_rest"] = mine[4][:, 1:].detach().clone().requires_grad_(True)
        image, alpha, info = rasterize_shard(
            *mine[:4],
            **sh,
            sh_degree=sh_degree,
            cameras=cameras,
            rows=list(rows),
            background=torch.tensor([0.2, 0.3, 0.4], dtype=torch.float32, device=device),
            visible_only=visible_only,
            capacity=capacity,
        )
        absgrad = info.retain_absgrad()  # AbsGS's sums over the whole scene's projection into this view
        weight = weights[rank].to(device)
        with torch.autograd.set_detect_anomaly(anomaly):
            ((image * weight).sum() + (alpha * weight[..., 0]).sum()).backward()
        intersections = info.check()  # with capacity: what the render did not read, raised here
        grads = [t.grad for t in mine[:4]]
        grads.append(torch.cat([sh["sh"].grad, sh["sh_rest"].grad], 1) if split else mine[4].grad)
        return {
            "image": image.detach().cpu(),
            "alpha": alpha.detach().cpu(),
            "intersections": intersections,
            "absgrad": absgrad.cpu(),
            "received": int(info.means2d.shape[0]),
            "grads": [g.cpu() for g in grads],
            "order": order,
        }
    finally:
        dist.destroy_process_group()


def sharded_scene(n, views, seed, width, height, sh_degree):
    """Random Gaussians around the origin, some beyond the views' sides ([means, quats, scales,
    opacities, sh]), ``views`` prepared cameras on an orbit around them, and a random weight image
    per view."""
    import math

    import torch
    from scenes import look_at_w2c

    from cdcgs.render import prepare_camera

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([3.0, 1.0, 1.0])  # some out of view
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.02
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
    K = torch.tensor([[0.9 * width, 0.0, 0.5 * width], [0.0, 0.9 * width, 0.5 * height], [0.0, 0.0, 1.0]])
    cameras = []
    for v in range(views):
        angle = 2 * math.pi * v / views
        w2c = torch.tensor(look_at_w2c((3.5 * math.sin(angle), -0.8, -3.5 * math.cos(angle))), dtype=torch.float32)
        cameras.append(prepare_camera(w2c, K, width, height))
    weights = [torch.rand(height, width, 3, generator=g) for _ in range(views)]
    return [means, quats, scales, opacities, sh], cameras, weights
