"""Sharded Gaussians (``cdcgs.train.shards``): each process holds a slice of the scene and renders
one view; the render and its gradients are those of one process rendering the whole scene."""

import pytest
import torch
from dist_tasks import ok, run_ranks, sharded_scene

from cdcgs.render import rasterize


@pytest.mark.parametrize(
    "rows, split, visible_only",
    [((70, 50), False, False), ((0, 90), True, False), ((70, 50), False, True), ((0, 90), True, True)],
    ids=["uneven", "an-empty-slice-sh-in-two", "uneven-visible-only", "an-empty-slice-visible-only"],
)
def test_a_sharded_render_is_the_whole_scenes_render(tmp_path, rows, split, visible_only):
    """Two processes (gloo, CPU), each with its slice (uneven, or one empty), each rendering its
    view: the image, the alpha and the intersection count are those of the whole scene's render
    of that view, bit for bit; each slice's gradients are the whole scene's gradient of the two
    views' losses, restricted to the slice, and AbsGS's sums of each view are the whole scene's
    of the Gaussians it received. ``split``: the SH as a trainer keeps them, degree 0 and the rest
    apart; ``visible_only``: each view sent only what it sees (fewer Gaussians, the same render)."""
    check_sharded_render(tmp_path, rows, split, visible_only, "gloo", torch.device("cpu"))


def test_a_sharded_render_into_slots_is_the_whole_scenes_render(tmp_path):
    """With ``capacity`` (nothing read on the host, as a captured step needs) the same render,
    and ``info.check()`` gives the view's count."""
    check_sharded_render(tmp_path, (70, 50), True, False, "gloo", torch.device("cpu"), capacity=4096)


@pytest.mark.parametrize("world, anomaly", [(2, False), (3, False), (2, True)], ids=["2", "3", "2-anomaly-mode"])
def test_the_backward_pass_takes_its_own_views_adjoint_while_the_others_gradients_travel(tmp_path, world, anomaly):
    """The backward pass posts the transfers that bring the other processes' gradients back, runs
    the projection's adjoint of this process's own view, and only then waits for those transfers
    (once), before the other views' adjoints read them: on a GPU its own adjoint runs during the
    transfers. The render and gradients stay the whole scene's (the tests above). Under anomaly
    detection, which reads every gradient for NaN as soon as it is returned, the transfers are
    waited for at once."""
    rows = (30, 20, 25)[:world]
    options = dict(rows=rows, record_order=True, anomaly=anomaly)
    outs = ok(run_ranks("sharded_render", world, tmp_path, timeout=60.0, **options))
    for rank, out in enumerate(outs):
        order = out["order"]
        if anomaly:
            assert "wait" not in order and sorted(order) == list(range(world)), order
            continue
        assert order[0] == rank and order[1] == "wait", order
        assert sorted(order[2:]) == [v for v in range(world) if v != rank], order


def test_a_sharded_render_keeps_float32_under_a_float64_default(tmp_path):
    """The processes' default dtype float64 (the tensors float32, as the render takes them): the
    gradients that come back are float32 still, and the same."""
    check_sharded_render(tmp_path, (70, 50), True, False, "gloo", torch.device("cpu"), default_float64=True)


@pytest.mark.skipif(
    not torch.cuda.is_available() or torch.cuda.device_count() < 2 or not torch.distributed.is_nccl_available(),
    reason="needs two GPUs and NCCL",
)
@pytest.mark.parametrize("visible_only", [False, True], ids=["every-gaussian", "visible-only"])
def test_a_sharded_render_on_two_gpus_is_the_whole_scenes_render(tmp_path, visible_only, device):
    """The same on two GPUs through NCCL, against one GPU's render of the whole scene (CUDA's
    atomic sums make the gradients equal to rounding, not bit for bit)."""
    if device == "cpu":
        pytest.skip("NCCL on two GPUs (the CPU case is the test above)")
    check_sharded_render(tmp_path, (700, 500), True, visible_only, "nccl", torch.device("cuda", 0))


def check_sharded_render(tmp_path, rows, split, visible_only, backend, device, default_float64=False, capacity=None):
    world, seed, width, height, degree = 2, 3, 40, 30, 2
    exact = device.type == "cpu"
    options = dict(rows=rows, seed=seed, width=width, height=height, split=split, visible_only=visible_only)
    if default_float64:
        options["default_float64"] = True
    if capacity is not None:
        options["capacity"] = capacity
    outs = run_ranks("sharded_render", world, tmp_path, timeout=180.0, backend=backend, **options)
    for rank, out in enumerate(outs):
        assert "result" in out, f"rank {rank}: {out.get('error')}: {out.get('message')}\n{out.get('traceback', '')}"
    scene, cameras, weights = sharded_scene(sum(rows), world, seed, width, height, degree)
    params = [t.to(device).clone().requires_grad_(True) for t in scene]
    background = torch.tensor([0.2, 0.3, 0.4], device=device)
    tolerance = dict(rtol=1e-5, atol=1e-7) if exact else dict(rtol=1e-4, atol=1e-6)
    total, absgrads = 0.0, []
    for view, camera in enumerate(cameras):
        image, alpha, info = rasterize(*params[:4], params[4], camera=camera, sh_degree=degree, background=background)
        got = outs[view]["result"]
        if exact:
            assert torch.equal(got["image"], image.detach()), view
            assert torch.equal(got["alpha"], alpha.detach()), view
        else:
            torch.testing.assert_close(got["image"], image.detach().cpu(), rtol=1e-6, atol=1e-6, msg=f"view {view}")
            torch.testing.assert_close(got["alpha"], alpha.detach().cpu(), rtol=1e-6, atol=1e-6, msg=f"view {view}")
        assert got["intersections"] == info.num_intersections > 0
        # the Gaussians the view received: all, or those it sees and the first of each slice
        received = torch.ones(sum(rows), dtype=torch.bool)
        if visible_only:
            received = (info.radii > 0).any(1).cpu()
            received[[sum(rows[:r]) for r in range(world) if rows[r]]] = True
            assert got["received"] == int(received.sum()) < sum(rows), view
        absgrads.append((info.retain_absgrad(), received))
        weight = weights[view].to(device)
        total = total + (image * weight).sum() + (alpha * weight[..., 0]).sum()
    total.backward()
    for view, (absgrad, received) in enumerate(absgrads):  # AbsGS's sums of each view, of what it received
        assert absgrad.abs().sum() > 0
        torch.testing.assert_close(outs[view]["result"]["absgrad"], absgrad.cpu()[received], **tolerance)
    start = 0
    for rank, size in enumerate(rows):
        for name, mine, whole in zip(
            ("means", "quats", "scales", "opacities", "sh"), outs[rank]["result"]["grads"], params
        ):
            expected = whole.grad[start : start + size].cpu()
            assert mine.shape == expected.shape, name
            torch.testing.assert_close(mine, expected, **tolerance, msg=f"rank {rank}: {name}")
        start += size
    assert sum(bool(p.grad.abs().sum() > 0) for p in params) == len(params)  # every parameter had a gradient


@pytest.mark.skipif(
    not torch.cuda.is_available() or torch.cuda.device_count() < 2 or not torch.distributed.is_nccl_available(),
    reason="needs two GPUs and NCCL",
)
@pytest.mark.parametrize("way", [{}, {"capacity": 4096}], ids=["every-gaussian", "into-slots"])
def test_a_mistake_on_one_of_two_gpus_raises_on_both(tmp_path, way, device):
    """The same through NCCL, whose transfers are queued on the GPU: a wrong tensor on one
    process, and a NaN on the other."""
    if device == "cpu":
        pytest.skip("NCCL on two GPUs (the CPU case is the test above)")
    for spoil, errors in [((1, "shape"), ["PeerError", "ValueError"]), ((0, "nan"), ["NonFiniteError"] * 2)]:
        outs = run_ranks(
            "sharded_render", 2, tmp_path, timeout=180.0, rows=(30, 30), spoil=spoil, backend="nccl", **way
        )
        assert [out.get("error") for out in outs] == errors, outs


def test_a_view_beyond_its_slots_raises_at_check(tmp_path):
    """A capacity below a view's pairs: CapacityError from ``info.check()`` on the process of
    that view alone, after a backward pass that both took (below both views' pairs: on both)."""
    scene, cameras, _ = sharded_scene(60, 2, 0, 40, 30, 2)
    counts = [rasterize(*scene, camera=camera, sh_degree=2)[2].num_intersections for camera in cameras]
    assert counts[0] != counts[1], counts
    for capacity in (min(counts), 8):
        outs = run_ranks("sharded_render", 2, tmp_path, timeout=60.0, rows=(30, 30), capacity=capacity)
        expected = ["CapacityError" if count > capacity else None for count in counts]
        assert [out.get("error") for out in outs] == expected, (capacity, outs)


def test_a_wrong_tensor_into_slots_under_a_float64_default_still_raises_on_both(tmp_path):
    """The process with the wrong tensor goes on with zeros (float32, whatever the default) to
    the end of the backward pass, so the other is not left waiting."""
    options = dict(rows=(30, 30), spoil=(1, "shape"), capacity=4096, default_float64=True)
    outs = run_ranks("sharded_render", 2, tmp_path, timeout=60.0, **options)
    assert [out.get("error") for out in outs] == ["PeerError", "ValueError"], outs


def test_a_sharded_render_names_what_is_wrong():
    """Bad arguments raise ValueError naming them (one process, a group of its own)."""
    import torch.distributed as dist
    from dist_tasks import free_port

    from cdcgs.train.shards import rasterize_shard

    scene, cameras, _ = sharded_scene(8, 2, 0, 16, 12, 1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{free_port()}", rank=0, world_size=1)
    try:
        good = dict(sh_degree=1, cameras=cameras[:1], rows=[8])
        for changes, match in [
            ({"cameras": cameras}, "cameras must be 1 PreparedCameras"),
            ({"rows": [8, 0]}, "rows must be 1 counts"),
            ({"rows": [-1]}, "rows must be 1 counts"),
            ({"rows": [0]}, "no Gaussians"),
            ({"rows": [7]}, "means"),
            ({"sh_degree": 4}, "sh_degree"),
            ({"sh_degree": 2}, "degree 2 needs 9"),
            ({"capacity": 0}, "capacity must be a positive int"),
            ({"capacity": 64, "visible_only": True}, "capacity and visible_only"),
        ]:
            with pytest.raises(ValueError, match=match):
                rasterize_shard(*scene, **{**good, **changes})
        with pytest.raises(ValueError, match="means is on meta"):
            rasterize_shard(scene[0].to("meta"), *scene[1:], **good)
        image, alpha, _ = rasterize_shard(*scene, **good)  # and one process is the whole scene
        whole, whole_alpha, _ = rasterize(*scene, camera=cameras[0], sh_degree=1)
        assert torch.equal(image, whole) and torch.equal(alpha, whole_alpha)
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize(
    "way", [{}, {"visible_only": True}, {"capacity": 4096}], ids=["every-gaussian", "visible-only", "into-slots"]
)
@pytest.mark.parametrize(
    "spoil, errors, messages",
    [
        ((1, "shape"), ["PeerError", "ValueError"], ["another process's arguments", "means must have shape"]),
        ((0, "nan"), ["NonFiniteError", "NonFiniteError"], ["means", "means"]),
    ],
    ids=["a-wrong-shape-on-one", "nan-on-one"],
)
def test_a_mistake_on_one_process_raises_on_every_one(tmp_path, spoil, errors, messages, way):
    """A wrong tensor or a NaN in one process's slice raises on both processes, which would
    otherwise wait for each other in an exchange: the run stops, with the reason, not hangs (into
    slots, at ``info.check()`` after the backward pass, which the process with the wrong tensor
    takes with zeros)."""
    outs = run_ranks("sharded_render", 2, tmp_path, timeout=60.0, rows=(30, 30), spoil=spoil, **way)
    assert [out.get("error") for out in outs] == errors, outs
    for out, message in zip(outs, messages):
        assert message in out["message"], out["message"]
