"""CDC-GS complexity: the high-pass maps and the per-Gaussian complexity kernel."""

import pytest
import reference
import torch
from conftest import look_at, make_scene

import cdcgs
from cdcgs.complexity import (
    ViewComplexity,
    complexity_map,
    complexity_over_views,
    gaussian_complexity,
    gaussian_complexity_views,
    high_frequency,
    luma,
)
from cdcgs.errors import NonFiniteError
from cdcgs.render import bin_view, prepare_camera, start_bin_view


def test_luma_uses_proper_rgb_weights():
    image = torch.tensor([[[255, 0, 0], [0, 255, 0], [0, 0, 255]]], dtype=torch.uint8)
    torch.testing.assert_close(luma(image), torch.tensor([[0.299, 0.587, 0.114]]))


@pytest.mark.parametrize("method", ["dwt", "dwt2", "sobel", "scharr", "laplacian"])
def test_constant_image_has_no_high_frequency(method):
    assert (high_frequency(torch.full((13, 17), 0.4), method) == 0).all()


def test_dwt_step_edge_responds_only_at_the_edge():
    # A vertical step between columns 4 and 5 (Haar pairs (4, 5)): one DWT level sees it only in
    # those two columns, where the detail is +-(b - a)/2, the same everywhere after normalising.
    y = torch.zeros(8, 12)
    y[:, 5:] = 1.0
    hf = high_frequency(y, "dwt")
    expected = torch.zeros(8, 12)
    expected[:, [4, 5]] = 1.0
    torch.testing.assert_close(hf, expected, atol=1e-6, rtol=0)
    # An edge on a Haar pair boundary (between columns 5 and 6) is invisible to one level:
    y = torch.zeros(8, 12)
    y[:, 6:] = 1.0
    assert high_frequency(y, "dwt").abs().max() < 1e-6
    # ... but not to two levels, unless it is also on a level-2 boundary (columns 7 and 8 are not).
    y = torch.zeros(8, 12)
    y[:, 6:] = 1.0
    hf2 = high_frequency(y, "dwt2")
    assert hf2[:, 4:8].max() > 0.5 and hf2[:, :4].abs().max() < 1e-6 and hf2[:, 8:].abs().max() < 1e-6


def test_odd_sizes_are_cropped_back():
    hf = high_frequency(torch.rand(13, 17), "dwt")
    assert hf.shape == (13, 17) and hf.min() == 0 and hf.max() == 1


def test_complexity_map_is_uint8_on_the_image_device(device):
    image = (torch.rand(20, 30, 3) * 255).to(torch.uint8).to(device)
    m = complexity_map(image)
    assert m.dtype == torch.uint8 and m.shape == (20, 30) and m.device.type == device and m.max() == 255


def dense_complexity(weights: torch.Tensor, hf: torch.Tensor, w_max: torch.Tensor | None = None):
    """Reference: per Gaussian max / sum / count over pixels of HF * max(w, 1e-4) / w_max, with
    w_max per pixel the largest floored weight unless given."""
    contributing = weights > 0
    floored = torch.where(contributing, weights.clamp_min(1e-4), torch.zeros_like(weights))
    if w_max is None:
        w_max = floored.max(dim=1).values.clamp_min(1e-4)
    value = torch.where(contributing, hf.reshape(-1, 1) * floored / w_max[:, None], torch.zeros_like(weights))
    return value.max(dim=0).values, value.sum(dim=0), contributing.sum(dim=0), value


def tile_list_alpha_max(scene, info, width, height) -> torch.Tensor:
    """[H*W] the CDC-GS code's w_max: the largest alpha (>= 1/255, <= 0.99, floored at 1e-4) of
    every Gaussian in the pixel's tile list, from a float64 projection."""
    d = [t.double() for t in scene.tensors()]
    mean2d, conic, _, opacity, _ = reference.project(*d[:4], scene.viewmat.double(), scene.K.double(), width, height)
    ys, xs = torch.meshgrid(torch.arange(height).double(), torch.arange(width).double(), indexing="ij")
    pix = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], -1)
    delta = mean2d[None] - pix[:, None]
    alpha = (opacity[None] * torch.exp(-0.5 * torch.einsum("pni,nij,pnj->pn", delta, conic, delta))).clamp(max=0.99)
    alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
    ranges, ids = info.tile_ranges.cpu(), info.sorted_gauss_ids.cpu().long()
    tile = (ys.reshape(-1) // 16 * info.tiles_x + xs.reshape(-1) // 16).long()
    w_max = torch.full((height * width,), 1e-4, dtype=torch.float64)
    for p in range(height * width):
        start, end = ranges[tile[p]].tolist()
        if end > start:
            w_max[p] = max(1e-4, alpha[p, ids[start:end]].max().item())
    return w_max


@pytest.mark.parametrize("w_max", ["weight", "alpha"])
@pytest.mark.parametrize(
    "seed, n, width, height",
    [(21, 300, 61, 37), (22, 300, 61, 37), (23, 1400, 40, 27)],  # the last: tile lists of several batches
)
def test_gaussian_complexity_matches_dense_reference(device, seed, n, width, height, w_max):
    scene = make_scene(n, width, height, sh_degree=0, seed=seed)
    if n > 1000:  # faint, so that pixels stay transparent through long lists
        scene.opacities = scene.opacities * 0.04
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=width, height=height
    )
    if n > 1000:
        lengths = info.tile_ranges[:, 1] - info.tile_ranges[:, 0]
        assert (lengths > 2 * 256).any(), "some tile list spans three batches"
    g = torch.Generator().manual_seed(seed)
    hf_map = (torch.rand(height, width, generator=g) * 255).to(torch.uint8)
    max_out, sum_out, count = gaussian_complexity(info, hf_map.to(device), w_max=w_max)
    d = [t.double() for t in scene.tensors()]
    *_, weights = reference.render(*d, viewmat=scene.viewmat.double(), K=scene.K.double(), width=width, height=height)
    pixel_w_max = tile_list_alpha_max(scene, info, width, height) if w_max == "alpha" else None
    ref_max, ref_sum, ref_count, _ = dense_complexity(weights, hf_map.double() / 255.0, pixel_w_max)
    assert (ref_count > 0).sum() > 20
    torch.testing.assert_close(count.cpu().long(), ref_count)
    torch.testing.assert_close(max_out.cpu().double(), ref_max, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(sum_out.cpu().double(), ref_sum, atol=1e-4, rtol=1e-4)
    if w_max == "alpha":  # the largest alpha over the tile list is at least the largest alpha * T
        assert (ref_max <= dense_complexity(weights, hf_map.double() / 255.0)[0] + 1e-12).all()
    alone, no_sum, no_count = gaussian_complexity(info, hf_map.to(device), w_max=w_max, sums=False)
    assert no_sum is None and no_count is None
    torch.testing.assert_close(alone, max_out, atol=0, rtol=0)
    # The tile lists alone (no colours, no blend) give the same Γ: the kernel finds each pixel's
    # stop itself.
    camera = prepare_camera(scene.viewmat, scene.K, width, height)
    lists = bin_view(*[t.to(device) for t in scene.tensors()[:4]], camera=camera)
    assert lists.colors is None and lists.last_contributor is None and lists.transmittance is None
    for name in ("tile_ranges", "sorted_gauss_ids", "means2d", "conics", "opacities"):
        torch.testing.assert_close(getattr(lists, name), getattr(info, name), atol=0, rtol=0)
    # Bit for bit, except the sums on CUDA: their atomic adds land in any order there.
    sum_rtol = 0 if device == "cpu" else 1e-5
    for got, expected, rtol in zip(
        gaussian_complexity(lists, hf_map.to(device), w_max=w_max), (max_out, sum_out, count), (0, sum_rtol, 0)
    ):
        torch.testing.assert_close(got, expected, atol=0, rtol=rtol)


@pytest.mark.parametrize(
    "seed, n, width, height",
    # the second: tile lists of several batches; the third: a few Gaussians, where the edges of
    # their footprints are many pixels' w_max
    [(21, 300, 61, 37), (23, 1400, 40, 27), (24, 6, 61, 37)],
)
def test_the_scattered_w_max_is_the_walks(device, seed, n, width, height):
    """w_max under the "alpha" rule found per list entry at its support box's pixels
    (``w_max_pass="scatter"``) is the largest alpha over each pixel's tile list (float64
    reference), and the Γ it gives is the per-pixel walk's: bit for bit on the CPU; on CUDA up to
    the sums' atomic order and the two kernels' own rounding of alpha."""
    import warp as wp

    from cdcgs.kernels import BLOCK_SIZE
    from cdcgs.kernels.blend import w_max_alpha_kernel

    scene = make_scene(n, width, height, sh_degree=0, seed=seed)
    if n > 1000:
        scene.opacities = scene.opacities * 0.04
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=width, height=height
    )
    hf_map = (torch.rand(height, width, generator=torch.Generator().manual_seed(seed)) * 255).to(torch.uint8)
    walk = gaussian_complexity(info, hf_map.to(device), w_max_pass="walk")
    scatter = gaussian_complexity(info, hf_map.to(device), w_max_pass="scatter")
    tolerances = (0, 0, 0) if device == "cpu" else (1e-6, 1e-5, 0)
    assert (walk[2] > 0).sum() >= min(20, n - 2)
    for got, expected, rtol in zip(scatter, walk, tolerances):
        torch.testing.assert_close(got, expected, atol=0, rtol=rtol)
    # the map itself, against the float64 reference
    w_max = torch.full((height * width,), 1e-4, device=device)
    tensors = [info.tile_ranges, info.sorted_gauss_ids, info.means2d.detach(), info.conics.detach(), info.opacities]
    dtypes = (wp.int32, wp.int32, wp.vec2, wp.vec3, wp.float32)
    wp.launch(
        w_max_alpha_kernel,
        info.tiles_x * info.tiles_y * BLOCK_SIZE,
        inputs=[
            *(wp.from_torch(t.contiguous(), dtype=d) for t, d in zip(tensors, dtypes)),
            width,
            height,
            info.tiles_x,
        ],
        outputs=[wp.from_torch(w_max)],
        device=wp.device_from_torch(w_max.device),
        block_dim=BLOCK_SIZE,
    )
    reference_w_max = tile_list_alpha_max(scene, info, width, height)
    assert (reference_w_max > 1e-4).sum() > 100
    torch.testing.assert_close(w_max.cpu().double(), reference_w_max, atol=1e-6, rtol=1e-4)
    with pytest.raises(ValueError, match="w_max_pass"):
        gaussian_complexity(info, hf_map.to(device), w_max_pass="sideways")


def test_bin_view_refuses_what_rasterize_refuses():
    scene = make_scene(40, 30, 20, sh_degree=0, seed=3)
    camera = prepare_camera(scene.viewmat, scene.K, 30, 20)
    means, quats, scales, opacities = scene.tensors()[:4]
    bad = means.clone()
    bad[5, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="means"):
        bin_view(bad, quats, scales, opacities, camera=camera)
    pending = start_bin_view(bad, quats, scales, opacities, camera=camera)  # queued: nothing read yet
    with pytest.raises(NonFiniteError, match="means"):
        pending.finish()
    with pytest.raises(ValueError, match="PreparedCamera"):
        bin_view(means, quats, scales, opacities, camera=scene.viewmat)
    with pytest.raises(ValueError, match="opacities"):
        bin_view(means, quats, scales, opacities[:-1], camera=camera)


def test_racy_max_keeps_one_pixel_per_tile(device):
    """The emulated race keeps, per tile and Gaussian, the value of one contributing pixel: never
    above the exact max, always one of the Gaussian's own values, the same for the same seed."""
    scene = make_scene(300, 61, 37, sh_degree=0, seed=23)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=61, height=37
    )
    hf_map = (torch.rand(37, 61, generator=torch.Generator().manual_seed(4)) * 255).to(torch.uint8).to(device)
    exact, exact_sum, exact_count = gaussian_complexity(info, hf_map)
    racy, racy_sum, racy_count = gaussian_complexity(info, hf_map, racy_seed=7)
    torch.testing.assert_close(racy_sum, exact_sum)
    torch.testing.assert_close(racy_count, exact_count)
    assert (racy <= exact + 1e-7).all()
    d = [t.double() for t in scene.tensors()]
    *_, weights = reference.render(*d, viewmat=scene.viewmat.double(), K=scene.K.double(), width=61, height=37)
    w_max = tile_list_alpha_max(scene, info, 61, 37)
    *_, values = dense_complexity(weights, hf_map.cpu().double() / 255.0, w_max)
    seen = exact_count.cpu() > 0
    gap = (values.T[seen] - racy.cpu().double()[seen][:, None]).abs().min(dim=1).values
    assert (gap < 1e-5).all(), "every racy max is the value of one of the Gaussian's pixels"
    many = exact_count.cpu() > 20
    assert (racy.cpu()[many] < exact.cpu()[many] - 1e-4).float().mean() > 0.3, "it is not the max"
    torch.testing.assert_close(gaussian_complexity(info, hf_map, racy_seed=7)[0], racy)
    assert not torch.equal(gaussian_complexity(info, hf_map, racy_seed=8)[0], racy)


def test_bad_map_is_refused(device):
    scene = make_scene(40, 32, 24, sh_degree=0, seed=3, hard_cases=False)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=32, height=24
    )
    with pytest.raises(ValueError, match="hf_map must be a uint8"):
        gaussian_complexity(info, torch.zeros(24, 31, dtype=torch.uint8, device=device))
    with pytest.raises(ValueError, match="hf_map must be a uint8"):
        gaussian_complexity(info, torch.zeros(24, 32, device=device))


@pytest.mark.parametrize("racy", [False, True])
def test_max_over_views_is_taken_in_place_into_the_running_max(device, racy):
    """ViewComplexity's max over pixels and views hands its running max to the kernel
    (``max_into``): the same as each view's max combined afterwards."""
    scene = make_scene(200, 40, 30, sh_degree=0, seed=5)
    tensors = [t.to(device) for t in scene.tensors()[:4]]
    g = torch.Generator().manual_seed(5)
    accumulator = ViewComplexity(200, device, racy_max=racy, racy_seed=3)
    expected = torch.zeros(200)
    for index, eye in enumerate([(0.3, -0.4, -5.0), (1.5, 0.2, -4.5), (-1.0, -1.0, -5.5)]):
        camera = prepare_camera(look_at(eye, (0.0, 0.0, 0.0)), scene.K, 40, 30)
        lists = bin_view(*tensors, camera=camera)
        hf_map = (torch.rand(30, 40, generator=g) * 255).to(torch.uint8).to(device)
        alone, _, _ = gaussian_complexity(lists, hf_map, racy_seed=3 + index if racy else None, sums=False)
        expected = torch.maximum(expected, alone.cpu())
        accumulator.add(lists, hf_map)
    assert (expected > 0).sum() > 50
    torch.testing.assert_close(accumulator.result().cpu(), expected, atol=0, rtol=0)
    with pytest.raises(ValueError, match="max_into"):
        gaussian_complexity(lists, hf_map, max_into=torch.zeros(199, device=device))


class _Rank:
    """Process ``rank`` of ``world`` whose reductions change nothing: its own share of the views."""

    def __init__(self, rank: int, world: int):
        self.rank, self.world = rank, world

    def all_reduce_(self, tensor, op="sum"):
        return tensor


class _Maps(list):
    """Complexity maps that note when each is read (``add`` reads its view's map)."""

    def __init__(self, maps, events):
        super().__init__(maps)
        self.events = events

    def __getitem__(self, index):
        self.events.append(("map", index))
        return super().__getitem__(index)


@pytest.mark.parametrize(
    "options, ranks, together",
    [
        ({}, None, 8),
        ({}, None, 2),
        ({}, (1, 2), 8),
        ({"w_max": "weight"}, None, 3),
        ({"pixel_aggregation": "mean", "view_aggregation": "mean"}, None, 1),
        ({"pixel_aggregation": "max", "view_aggregation": "mean"}, (1, 2), 1),
        ({"racy_max": True, "racy_seed": 7}, None, 1),
        ({"racy_max": True, "racy_seed": 7}, (0, 2), 1),
    ],
)
def test_the_gamma_pass_queues_the_next_view_before_it_finishes_this_one(device, options, ranks, together, monkeypatch):
    """complexity_over_views with start_bin_view's pending lists: view i + 1 is started before
    view i is finished (so that the GPU projects and counts it while the host waits for view i's
    count), and the views are measured ``together`` at a time once the last of them is finished
    (the exact max over pixels and views: GAMMA_VIEWS_PER_LAUNCH of them in one launch; the other
    aggregations and the racy emulation one at a time); with finished lists, bins and maps in
    the same groups. Γ is that of the loop before the change (bin_view, then add, each view
    seeded with its own index), bit for bit but for the sums' atomic adds on CUDA, for each
    aggregation, the racy emulation and a rank's share."""
    monkeypatch.setattr(cdcgs.complexity, "GAMMA_VIEWS_PER_LAUNCH", max(together, 2))
    scene = make_scene(200, 40, 30, sh_degree=0, seed=6)
    tensors = [t.to(device) for t in scene.tensors()[:4]]
    eyes = [(0.3, -0.4, -5.0), (1.5, 0.2, -4.5), (-1.0, -1.0, -5.5), (0.0, 1.2, -5.0), (-0.8, 0.5, -4.8)]
    cameras = [prepare_camera(look_at(eye, (0.0, 0.0, 0.0)), scene.K, 40, 30) for eye in eyes]
    g = torch.Generator().manual_seed(6)
    maps = [(torch.rand(30, 40, generator=g) * 255).to(torch.uint8).to(device) for _ in eyes]
    rank, world = ranks or (0, 1)
    mine = list(range(rank, len(eyes), world))
    stub = _Rank(rank, world) if ranks else None
    events = []

    class Recorded:
        def __init__(self, index):
            events.append(("start", index))
            if device == "cuda":  # queued without a blocking copy or a read of the device
                torch.cuda.set_sync_debug_mode("error")
            try:
                self.index, self.pending = index, start_bin_view(*tensors, camera=cameras[index])
            finally:
                if device == "cuda":
                    torch.cuda.set_sync_debug_mode("default")

        def finish(self):
            events.append(("finish", self.index))
            info = self.pending.finish()
            assert self.pending.finish() is info  # a second call gives the same lists
            return info

    got = complexity_over_views(Recorded, _Maps(maps, events), 200, device, ranks=stub, **options)
    groups = [mine[i : i + together] for i in range(0, len(mine), together)]
    expected_order = [("start", mine[0])]
    for group in groups:
        for index in group:
            position = mine.index(index)
            if position + 1 < len(mine):
                expected_order.append(("start", mine[position + 1]))
            expected_order.append(("finish", index))
        expected_order += [("map", index) for index in group]
    assert events == expected_order

    events.clear()

    def finished(index):
        events.append(("bins", index))
        return bin_view(*tensors, camera=cameras[index])

    one_at_a_time = complexity_over_views(finished, _Maps(maps, events), 200, device, ranks=stub, **options)
    assert events == [event for group in groups for event in [("bins", i) for i in group] + [("map", i) for i in group]]

    # The loop before the change, written out.
    seed = options.get("racy_seed", 0)
    accumulator = ViewComplexity(200, device, **options)
    for index in mine:
        info = bin_view(*tensors, camera=cameras[index])
        accumulator.views_added = seed + index
        accumulator.add(info, maps[index])
    expected = accumulator.result()
    assert (expected > 0).sum() > 30
    sums = options.get("pixel_aggregation") == "mean" or options.get("view_aggregation") == "mean"
    rtol = 1e-5 if sums and device == "cuda" else 0
    torch.testing.assert_close(got, expected, atol=0, rtol=rtol)
    torch.testing.assert_close(one_at_a_time, expected, atol=0, rtol=rtol)


@pytest.mark.parametrize("w_max", ["alpha", "weight"])
def test_views_measured_in_one_launch_give_the_max_of_one_launch_each(device, w_max, monkeypatch):
    """gaussian_complexity_views (several views' tiles in one launch, their maxima taken into one
    running max) against gaussian_complexity of each view in turn, bit for bit: five views, two of
    another image size (so that complexity_over_views launches them apart), Gaussians that some
    views do not see. With GAMMA_VIEWS_BYTES too small for two views, one view a launch, the same
    Γ. A view binned into too few slots adds nothing (its overflow flag, on the device); into
    enough, its own max. Mismatched views, maps or ``max_into`` are refused."""
    scene = make_scene(300, 40, 30, sh_degree=0, seed=8)
    tensors = [t.to(device) for t in scene.tensors()[:4]]
    eyes = [(0.3, -0.4, -5.0), (1.5, 0.2, -4.5), (-1.0, -1.0, -5.5), (0.0, 1.2, -5.0), (-2.5, 0.5, -3.0)]
    sizes = [(40, 30), (40, 30), (36, 33), (36, 33), (40, 30)]
    cameras = [prepare_camera(look_at(eye, (0.0, 0.0, 0.0)), scene.K, w, h) for eye, (w, h) in zip(eyes, sizes)]
    g = torch.Generator().manual_seed(8)
    maps = [(torch.rand(h, w, generator=g) * 255).to(torch.uint8).to(device) for w, h in sizes]
    infos = [bin_view(*tensors, camera=camera) for camera in cameras]
    views_max = []
    for info, hf_map in zip(infos, maps):
        alone, _, _ = gaussian_complexity(info, hf_map, w_max=w_max, sums=False)
        views_max.append(alone.cpu())
    expected = torch.stack(views_max).amax(0)
    assert (expected > 0).sum() > 100
    assert ((torch.stack(views_max) > 0).sum(0) < len(eyes)).sum() > 20  # some views miss some Gaussians
    start = torch.rand(300, generator=g).to(device) * 0.2  # a running max from earlier views
    into = start.clone()
    assert gaussian_complexity_views(infos[:2] + infos[4:], [maps[0], maps[1], maps[4]], into, w_max) is into
    mine = torch.maximum(start.cpu(), torch.stack([views_max[0], views_max[1], views_max[4]]).amax(0))
    torch.testing.assert_close(into.cpu(), mine, atol=0, rtol=0)
    for together in (8, 2):
        monkeypatch.setattr(cdcgs.complexity, "GAMMA_VIEWS_PER_LAUNCH", together)
        got = complexity_over_views(lambda i: infos[i], maps, 300, device, w_max=w_max)
        torch.testing.assert_close(got.cpu(), expected, atol=0, rtol=0)
    monkeypatch.setattr(cdcgs.complexity, "GAMMA_VIEWS_BYTES", 1)
    got = complexity_over_views(lambda i: infos[i], maps, 300, device, w_max=w_max)
    torch.testing.assert_close(got.cpu(), expected, atol=0, rtol=0)
    # A view binned into too few slots (its overflow flag set on the device) adds nothing.
    short = bin_view(*tensors, camera=cameras[1], capacity=infos[1].num_intersections - 1)
    untouched = gaussian_complexity_views([short], [maps[1]], start.clone(), w_max)
    torch.testing.assert_close(untouched, start, atol=0, rtol=0)
    beside = gaussian_complexity_views([infos[0], short], maps[:2], start.clone(), w_max)
    torch.testing.assert_close(beside.cpu(), torch.maximum(start.cpu(), views_max[0]), atol=0, rtol=0)
    fits = bin_view(*tensors, camera=cameras[1], capacity=infos[1].num_intersections)
    torch.testing.assert_close(
        gaussian_complexity_views([fits], [maps[1]], start.clone(), w_max).cpu(),
        torch.maximum(start.cpu(), views_max[1]),
        atol=0,
        rtol=0,
    )
    with pytest.raises(ValueError, match="one image size"):
        gaussian_complexity_views(infos[1:3], maps[1:3], start.clone())
    with pytest.raises(ValueError, match="as many maps"):
        gaussian_complexity_views(infos[:2], maps[:1], start.clone())
    with pytest.raises(ValueError, match="hf_map must be a uint8"):
        gaussian_complexity_views(infos[:2], [maps[0], maps[2]], start.clone())
    with pytest.raises(ValueError, match="max_into"):
        gaussian_complexity_views(infos[:2], maps[:2], torch.zeros(299, device=device))


@pytest.mark.parametrize("options", [{}, {"w_max": "weight"}, {"pixel_aggregation": "mean"}, {"racy_max": True}])
def test_the_gamma_pass_bins_into_slots_reads_once_and_counts_again_after_an_overflow(device, options):
    """Views binned into slots (bin_view(capacity=...)): the same lists and Γ as counted ones,
    nothing read back until the pass's end. When one view's slots are too few, its lists are
    incomplete: under the exact max over pixels and views that view adds nothing and it alone is
    measured again with bins(i, counted=True); under the other aggregations (its values in the
    sums already) the whole pass is taken again so. Either way the counted Γ. NaN in an input
    raises NonFiniteError at the end of the pass; a capacity out of range is refused."""
    scene = make_scene(200, 40, 30, sh_degree=0, seed=6)
    tensors = [t.to(device) for t in scene.tensors()[:4]]
    eyes = [(0.3, -0.4, -5.0), (1.5, 0.2, -4.5), (-1.0, -1.0, -5.5)]
    cameras = [prepare_camera(look_at(eye, (0.0, 0.0, 0.0)), scene.K, 40, 30) for eye in eyes]
    g = torch.Generator().manual_seed(7)
    maps = [(torch.rand(30, 40, generator=g) * 255).to(torch.uint8).to(device) for _ in eyes]
    counts = [bin_view(*tensors, camera=camera).num_intersections for camera in cameras]
    assert min(counts) > 100
    expected = complexity_over_views(lambda i: bin_view(*tensors, camera=cameras[i]), maps, 200, device, **options)
    assert (expected > 0).sum() > 30
    alone = options in ({}, {"w_max": "weight"})  # the exact max: an overflowed view measured again alone

    def slotted(slots, inputs=tensors):
        calls = []

        def bins(index, counted=False):
            calls.append((index, counted))
            if counted:
                return bin_view(*inputs, camera=cameras[index])
            if device == "cuda":  # binned into slots without a blocking copy or a read of the device
                torch.cuda.set_sync_debug_mode("error")
            try:
                return bin_view(*inputs, camera=cameras[index], capacity=slots[index])
            finally:
                if device == "cuda":
                    torch.cuda.set_sync_debug_mode("default")

        return bins, calls

    rtol = 1e-5 if options.get("pixel_aggregation") == "mean" and device == "cuda" else 0  # atomic sums
    bins, calls = slotted([count + 7 for count in counts])
    torch.testing.assert_close(complexity_over_views(bins, maps, 200, device, **options), expected, atol=0, rtol=rtol)
    assert calls == [(0, False), (1, False), (2, False)]
    bins, calls = slotted([counts[0], counts[1] - 1, counts[2]])  # view 1 overflows by one pair
    torch.testing.assert_close(complexity_over_views(bins, maps, 200, device, **options), expected, atol=0, rtol=rtol)
    again = [(1, True)] if alone else [(0, True), (1, True), (2, True)]
    assert calls == [(0, False), (1, False), (2, False), *again]
    bins, calls = slotted([counts[0] - 1, counts[1], counts[2] - 1])  # views 0 and 2
    torch.testing.assert_close(complexity_over_views(bins, maps, 200, device, **options), expected, atol=0, rtol=rtol)
    again = [(0, True), (2, True)] if alone else [(0, True), (1, True), (2, True)]
    assert calls == [(0, False), (1, False), (2, False), *again]
    bad = [t.clone() for t in tensors]
    bad[0][5, 1] = float("nan")
    bins, _ = slotted(counts, bad)
    with pytest.raises(NonFiniteError, match="means"):
        complexity_over_views(bins, maps, 200, device, **options)
    with pytest.raises(ValueError, match="capacity"):
        bin_view(*tensors, camera=cameras[0], capacity=0)
