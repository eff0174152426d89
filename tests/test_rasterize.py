"""The Warp rasterizer against the dense float64 torch reference: forward values and VJPs."""

import pytest
import reference
import torch
from conftest import make_scene

import cdcgs
import cdcgs.render
from cdcgs.kernels import BLOCK_SIZE, TILE_SIZE

SCENES = {
    # name: (n, width, height, seed)
    "hard-50": (50, 45, 29, 1),
    "hard-300": (300, 61, 37, 2),
    "hard-500": (500, 83, 50, 3),
}


def _render_both(scene, device, *, sh_degree=None, background=None, antialiased=False, requires_grad=False):
    tensors = [t.to(device).clone().requires_grad_(requires_grad) for t in scene.tensors()]
    bg = None
    if background is not None:
        bg = torch.tensor(background, device=device).requires_grad_(requires_grad)
    image, alpha, info = cdcgs.rasterize(
        *tensors,
        viewmat=scene.viewmat,
        K=scene.K,
        width=scene.width,
        height=scene.height,
        sh_degree=sh_degree,
        background=bg,
        antialiased=antialiased,
        render_depth=True,
    )
    ref_tensors = [t.double().clone().requires_grad_(requires_grad) for t in scene.tensors()]
    ref_bg = (
        torch.tensor(background, dtype=torch.float64).requires_grad_(requires_grad) if background is not None else None
    )
    ref = reference.render(
        *ref_tensors,
        viewmat=scene.viewmat.double(),
        K=scene.K.double(),
        width=scene.width,
        height=scene.height,
        sh_degree=sh_degree,
        background=ref_bg,
        antialiased=antialiased,
    )
    return (tensors, bg, image, alpha, info), (ref_tensors, ref_bg, ref)


@pytest.mark.parametrize("scene_name", SCENES)
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("antialiased", [False, True])
def test_forward_matches_reference(device, scene_name, sh_degree, antialiased):
    n, w, h, seed = SCENES[scene_name]
    scene = make_scene(n, w, h, sh_degree=sh_degree, seed=seed)
    (_, _, image, alpha, info), (_, _, (ref_image, ref_alpha, ref_depth, ref_weights)) = _render_both(
        scene, device, background=[0.2, 0.5, 0.9], antialiased=antialiased
    )
    assert image.shape == (h, w, 3) and alpha.shape == (h, w) and image.device.type == device
    # The scene must exercise the cases it claims: culled and visible Gaussians, dense coverage.
    assert 0 < info.visible.sum() < n
    assert ref_alpha.max() > 0.9
    torch.testing.assert_close(image.double().cpu(), ref_image, atol=1e-4, rtol=0)
    torch.testing.assert_close(alpha.double().cpu(), ref_alpha, atol=1e-4, rtol=0)
    # Expected depth is in scene units (about 5): compare relative to it.
    torch.testing.assert_close(info.depth.double().cpu(), ref_depth, atol=1e-4 * ref_depth.max().item(), rtol=0)
    # Every Gaussian that composites somewhere is reported visible.
    composited = (ref_weights > 0).any(0)
    assert not (composited & ~info.visible.cpu()).any()


def test_early_termination_matches_reference(device):
    """A stack of nearly opaque Gaussians: compositing stops before transmittance drops below 1e-4."""
    n = 40
    g = torch.Generator().manual_seed(7)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.05, 0.05, 0.5]) + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.full((n, 3), 0.3)
    opacities = torch.full((n,), 0.9)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]])
    view = torch.eye(4)
    image, alpha, info = cdcgs.rasterize(
        *(t.to(device) for t in (means, quats, scales, opacities)),
        colors=colors.to(device),
        viewmat=view,
        K=K,
        width=32,
        height=32,
        background=[1.0, 1.0, 1.0],
    )
    d = [t.double() for t in (means, quats, scales, opacities)]
    ref_image, ref_alpha, _, _ = reference.render(
        *d,
        colors=colors.double(),
        viewmat=view.double(),
        K=K.double(),
        width=32,
        height=32,
        background=torch.ones(3, dtype=torch.float64),
    )
    ranges = info.tile_ranges.cpu().view(info.tiles_y, info.tiles_x, 2)
    ends = ranges[..., 1].repeat_interleave(TILE_SIZE, 0).repeat_interleave(TILE_SIZE, 1)[:32, :32]
    stopped = info.last_contributor.cpu() < ends - 1
    assert stopped.sum() > 100, "the scene must make many pixels stop early"
    assert (1 - alpha[stopped.to(device)]).min() >= 1e-4
    torch.testing.assert_close(image.double().cpu(), ref_image, atol=1e-4, rtol=0)
    torch.testing.assert_close(alpha.double().cpu(), ref_alpha, atol=1e-4, rtol=0)


def test_colors_instead_of_sh(device):
    scene = make_scene(120, 40, 30, sh_degree=0, seed=4)
    colors = torch.rand(120, 3, generator=torch.Generator().manual_seed(0))
    image, _, _ = cdcgs.rasterize(
        *(t.to(device) for t in scene.tensors()[:4]),
        colors=colors.to(device),
        viewmat=scene.viewmat,
        K=scene.K,
        width=40,
        height=30,
    )
    d = [t.double() for t in scene.tensors()[:4]]
    ref_image, _, _, _ = reference.render(
        *d, colors=colors.double(), viewmat=scene.viewmat.double(), K=scene.K.double(), width=40, height=30
    )
    torch.testing.assert_close(image.double().cpu(), ref_image, atol=1e-4, rtol=0)


def test_prepared_camera_renders_what_the_matrices_render(device):
    """A camera prepared once (``prepare_camera``) gives the render of the same matrices passed
    directly: bit for bit forward, and the same gradients (up to the order of the backward pass's
    float atomics on CUDA); it is immutable and reusable."""
    import dataclasses

    scene = make_scene(150, 45, 29, sh_degree=2, seed=5)
    camera = cdcgs.prepare_camera(scene.viewmat, scene.K, 45, 29, near_plane=0.05)
    assert isinstance(camera, cdcgs.PreparedCamera)
    assert (camera.width, camera.height, camera.near_plane) == (45, 29, 0.05)
    view = scene.viewmat.double()
    center = -view[:3, :3].T @ view[:3, 3]
    torch.testing.assert_close(
        torch.tensor([camera.center[i] for i in range(3)], dtype=torch.float64), center, atol=1e-5, rtol=0
    )
    assert camera.camera.width == 45 and camera.camera.near == pytest.approx(0.05)
    with pytest.raises(dataclasses.FrozenInstanceError):
        camera.width = 10
    results = []
    for kwargs in [
        dict(camera=camera),
        dict(viewmat=scene.viewmat, K=scene.K, width=45, height=29, near_plane=0.05),
        dict(camera=camera),
    ]:
        tensors = [t.to(device).requires_grad_() for t in scene.tensors()]
        image, alpha, info = cdcgs.rasterize(*tensors, render_depth=True, **kwargs)
        (image.sum() + info.depth.sum()).backward()
        results.append([image, alpha, info.depth, info.radii, *(t.grad for t in tensors)])
    for k, (prepared, direct, again) in enumerate(zip(*results)):
        if k < 4 or device == "cpu":
            assert torch.equal(prepared, direct) and torch.equal(again, direct)
        else:
            tol = 1e-5 * direct.abs().max().item()
            torch.testing.assert_close(prepared, direct, atol=tol, rtol=0)
            torch.testing.assert_close(again, direct, atol=tol, rtol=0)


def test_camera_comes_one_way():
    scene = make_scene(10, 16, 16, sh_degree=0, seed=1)
    camera = cdcgs.prepare_camera(scene.viewmat, scene.K, 16, 16)
    tensors = scene.tensors()
    loose = dict(viewmat=scene.viewmat, K=scene.K, width=16, height=16)
    with pytest.raises(ValueError, match="not both"):
        cdcgs.rasterize(*tensors, camera=camera, **loose)
    with pytest.raises(ValueError, match=r"not both.*near_plane"):
        cdcgs.rasterize(*tensors, camera=camera, near_plane=0.1)
    with pytest.raises(ValueError, match="missing: viewmat, K, width, height"):
        cdcgs.rasterize(*tensors)
    with pytest.raises(ValueError, match="missing: K"):
        cdcgs.rasterize(*tensors, **{**loose, "K": None})
    with pytest.raises(ValueError, match="camera must be a PreparedCamera"):
        cdcgs.rasterize(*tensors, camera=camera.camera)
    for bad, match in [
        (dict(width=0), "width must be a positive int"),
        (dict(K=torch.zeros(3, 3)), "positive focal lengths"),
    ]:
        with pytest.raises(ValueError, match=match):
            cdcgs.prepare_camera(**{**loose, **bad})


# Stated per-tensor tolerances for vector-Jacobian products: max abs error within REL of the
# largest reference entry (float32 kernels against float64 autograd).
VJP_REL = {"means": 1e-3, "quats": 1e-3, "scales": 1e-3, "opacities": 1e-3, "sh": 1e-3, "background": 1e-3}


@pytest.mark.parametrize("scene_name", ["hard-50", "hard-300"])
@pytest.mark.parametrize("sh_degree", [0, 3])
@pytest.mark.parametrize("antialiased", [False, True])
def test_vjp_matches_reference(device, scene_name, sh_degree, antialiased):
    n, w, h, seed = SCENES[scene_name]
    scene = make_scene(n, w, h, sh_degree=sh_degree, seed=seed)
    (tensors, bg, image, alpha, info), (ref_tensors, ref_bg, ref) = _render_both(
        scene, device, background=[0.3, 0.1, 0.6], antialiased=antialiased, requires_grad=True
    )
    g = torch.Generator().manual_seed(seed)
    cot_image, cot_alpha, cot_depth = (
        torch.randn(h, w, 3, generator=g),
        torch.randn(h, w, generator=g),
        torch.randn(h, w, generator=g),
    )
    loss = (
        (image * cot_image.to(device)).sum()
        + (alpha * cot_alpha.to(device)).sum()
        + (info.depth * cot_depth.to(device)).sum()
    )
    loss.backward()
    ref_image, ref_alpha, ref_depth, _ = ref
    ((ref_image * cot_image).sum() + (ref_alpha * cot_alpha).sum() + (ref_depth * cot_depth).sum()).backward()
    names = ["means", "quats", "scales", "opacities", "sh", "background"]
    for name, ours, theirs in zip(names, [*tensors, bg], [*ref_tensors, ref_bg]):
        expected = theirs.grad
        assert expected.abs().max() > 0, f"{name}: the reference gradient is zero, the test would prove nothing"
        tol = VJP_REL[name] * expected.abs().max().item()
        torch.testing.assert_close(
            ours.grad.double().cpu(), expected, atol=tol, rtol=0, msg=lambda m, name=name: f"{name}: {m}"
        )


@pytest.mark.parametrize("sh_degree", [1, 2])
def test_sh_vjp_below_the_stored_degree(device, sh_degree):
    """Degree-3 coefficients rendered at degree 1 or 2: the SH adjoint matches the reference at
    every degree, and coefficients above the degree get exactly zero."""
    n, w, h, seed = SCENES["hard-50"]
    scene = make_scene(n, w, h, sh_degree=3, seed=seed, hard_cases=False)
    (tensors, _, image, _, _), (ref_tensors, _, ref) = _render_both(
        scene, device, sh_degree=sh_degree, requires_grad=True
    )
    cot = torch.randn(h, w, 3, generator=torch.Generator().manual_seed(seed))
    (image * cot.to(device)).sum().backward()
    (ref[0] * cot).sum().backward()
    used = (sh_degree + 1) ** 2
    # An image-only loss: the backward pass also runs without an alpha gradient here.
    for name, ours, theirs in zip(["means", "quats", "scales", "opacities", "sh"], tensors, ref_tensors):
        tol = 1e-3 * theirs.grad.abs().max().item()
        torch.testing.assert_close(
            ours.grad.double().cpu(), theirs.grad, atol=tol, rtol=0, msg=lambda m, name=name: f"{name}: {m}"
        )
    assert tensors[4].grad[:, :used].abs().max() > 0
    assert torch.equal(tensors[4].grad[:, used:].cpu(), torch.zeros_like(tensors[4].grad[:, used:].cpu()))


def _backward_with_positional_gradients(device, hard_cases: bool):
    """The info of a 48 x 32 render of 80 Gaussians after an L1 loss's backward pass, with the
    positional gradient and AbsGS's sums kept."""
    scene = make_scene(80, 48, 32, sh_degree=1, seed=5, hard_cases=hard_cases)
    tensors = [t.to(device).requires_grad_() for t in scene.tensors()]
    image, _, info = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=48, height=32)
    info.means2d.retain_grad()
    info.retain_absgrad()
    target = torch.rand(32, 48, 3, generator=torch.Generator().manual_seed(1)).to(device)
    (image - target).abs().mean().backward()
    return info


def test_positional_gradient_is_ndc_scaled_means2d_gradient(device):
    info = _backward_with_positional_gradients(device, hard_cases=False)
    grad = info.means2d.grad.cpu().double()
    expected = (grad * torch.tensor([24.0, 16.0], dtype=torch.float64)).norm(dim=-1)
    torch.testing.assert_close(info.positional_gradient().cpu().double(), expected)
    # AbsGS: per-pixel absolute values summed, so at least the absolute value of the sum.
    absgrad = info.means2d_absgrad.cpu().double()
    assert (absgrad + 1e-9 >= grad.abs()).all()
    assert (absgrad[info.visible.cpu()] > 0).any()
    assert (absgrad[~info.visible.cpu()] == 0).all()


def test_statistics_of_a_render_are_added_in_place_as_3dgs_adds_them(device):
    """accumulate_statistics (one kernel) against the float64 formula on the render's own
    gradients and radii: for every Gaussian with both radii > 0 the NDC-scaled gradient norm
    (AbsGS's sums with ``absolute``) is added, 1 counted, the largest radius kept; the others stay
    as they were. Bad accumulators are refused, naming them."""
    info = _backward_with_positional_gradients(device, hard_cases=True)
    radii = info.radii.cpu()
    seen = (radii > 0).all(dim=-1)
    assert seen.any() and (~seen).any()
    g = torch.Generator().manual_seed(2)
    start = [torch.rand(80, generator=g, dtype=torch.float64) * s for s in (1e-3, 5.0, 30.0)]
    for absolute, pixels in ((False, info.means2d.grad), (True, info.means2d_absgrad)):
        grad_sum, count, max_radius = (t.float().to(device) for t in start)
        for _ in range(2):
            info.accumulate_statistics(grad_sum, count, max_radius, absolute=absolute)
        norm = (pixels.cpu().double() * torch.tensor([24.0, 16.0], dtype=torch.float64)).norm(dim=-1)
        expected_sum = start[0].float().double() + 2 * torch.where(seen, norm, torch.zeros_like(norm))
        once = start[1].float() + seen.float()  # float32 additions of 1, as the kernel makes them
        expected_count = (once + seen.float()).double()
        largest = torch.where(seen, radii.max(dim=-1).values.double(), torch.zeros(80, dtype=torch.float64))
        expected_radius = torch.maximum(start[2].float().double(), largest)
        torch.testing.assert_close(grad_sum.cpu().double(), expected_sum, rtol=1e-6, atol=1e-12)
        torch.testing.assert_close(count.cpu().double(), expected_count, rtol=0, atol=0)
        torch.testing.assert_close(max_radius.cpu().double(), expected_radius, rtol=0, atol=0)
        assert (grad_sum.cpu()[~seen] == start[0].float()[~seen]).all(), "unseen Gaussians untouched"
    ok = torch.zeros(80, device=device)
    for bad, name in (
        ((ok.double(), ok, ok), "grad_sum"),
        ((ok, ok[:-1], ok), "count"),
        ((ok, ok, torch.zeros(80, 2, device=device)[:, 0]), "max_radius"),
    ):
        with pytest.raises(ValueError, match=name):
            info.accumulate_statistics(*bad)


def test_backward_without_sums_gives_the_same_gradients(device):
    """Without ``retain_absgrad()`` and a depth term in the loss the backward pass runs the blend
    adjoint without those sums (``blend_backward_lean_kernel``): the parameters' gradients must not
    change, ``means2d_absgrad`` stays None and asking for the AbsGS gradient says what to call."""
    scene = make_scene(60, 40, 24, sh_degree=1, seed=9, hard_cases=False)
    target = torch.rand(24, 40, 3, generator=torch.Generator().manual_seed(3)).to(device)
    grads = []
    for sums in (False, True):
        tensors = [t.to(device).requires_grad_() for t in scene.tensors()]
        image, _, info = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=40, height=24)
        if sums:
            info.retain_absgrad()
        ((image - target) ** 2).mean().backward()
        assert (info.means2d_absgrad is not None) == sums
        grads.append([t.grad for t in tensors])
    with pytest.raises(RuntimeError, match="retain_absgrad"):
        tensors = [t.to(device) for t in scene.tensors()]
        cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=40, height=24)[2].positional_gradient(
            absolute=True
        )
    for lean, full in zip(*grads):
        assert full.abs().max() > 0
        torch.testing.assert_close(lean, full, atol=1e-6 * full.abs().max().item(), rtol=1e-5)


@pytest.mark.skipif(
    not torch.cuda.is_available(), reason="the two ways of adding the adjoint's sums differ on CUDA only"
)
@pytest.mark.parametrize("variant", ["block", "warp"])
@pytest.mark.parametrize("sums", [False, True])
def test_blend_adjoint_over_several_batches_matches_reference(monkeypatch, variant, sums):
    """Both CUDA blend adjoints (``BLEND_BACKWARD_CUDA``: the warps' sums met in shared memory, or
    added by each warp) against the float64 reference, on faint large Gaussians whose tile lists run
    over several batches of BLOCK_SIZE, so that the shared sums are read and zeroed between batches;
    with the depth and AbsGS sums (``sums``) and without."""
    monkeypatch.setattr(cdcgs.render, "BLEND_BACKWARD_CUDA", variant)
    scene = make_scene(900, 40, 24, sh_degree=1, seed=11, hard_cases=False)
    g = torch.Generator().manual_seed(5)
    scene.scales *= 3.0
    scene.opacities = 0.01 + 0.03 * torch.rand(900, generator=g)
    (tensors, _, image, _, info), (ref_tensors, _, ref) = _render_both(scene, "cuda", requires_grad=True)
    ranges = info.tile_ranges.cpu()
    assert (ranges[:, 1] - ranges[:, 0]).max() > 2 * BLOCK_SIZE, "the lists must span several batches"
    cot_image = torch.randn(24, 40, 3, generator=g)
    cot_depth = torch.randn(24, 40, generator=g)
    loss = (image * cot_image.cuda()).sum()
    ref_image, _, ref_depth, _ = ref
    ref_loss = (ref_image * cot_image).sum()
    if sums:
        loss = loss + (info.depth * cot_depth.cuda()).sum()
        ref_loss = ref_loss + (ref_depth * cot_depth).sum()
    loss.backward()
    ref_loss.backward()
    for name, ours, theirs in zip(["means", "quats", "scales", "opacities", "sh"], tensors, ref_tensors):
        expected = theirs.grad
        assert expected.abs().max() > 0, f"{name}: the reference gradient is zero, the test would prove nothing"
        torch.testing.assert_close(
            ours.grad.double().cpu(),
            expected,
            atol=VJP_REL[name] * expected.abs().max().item(),
            rtol=0,
            msg=lambda m, name=name: f"{variant}, {name}: {m}",
        )


@pytest.mark.parametrize("sums", [False, True])
def test_the_chunked_adjoint_matches_reference(device, monkeypatch, sums):
    """``BLEND_CHUNK``: the adjoint walks each tile's list in chunks of 256 entries, one block
    each, a pixel that composites past its chunk starting from the forward pass's checkpoint at
    the chunk's end. On faint large Gaussians whose walks span several chunks: the float64
    reference's gradients, and those of the whole-tile adjoint up to float rounding."""
    scene = make_scene(900, 40, 24, sh_degree=1, seed=11, hard_cases=False)
    g = torch.Generator().manual_seed(5)
    scene.scales *= 3.0
    scene.opacities = 0.01 + 0.03 * torch.rand(900, generator=g)
    cot_image, cot_depth = torch.randn(24, 40, 3, generator=g), torch.randn(24, 40, generator=g)
    grads = {}
    for chunk in (0, 256):
        monkeypatch.setattr(cdcgs.render, "BLEND_CHUNK", chunk)
        (tensors, _, image, _, info), (ref_tensors, _, ref) = _render_both(scene, device, requires_grad=True)
        loss = (image * cot_image.to(device)).sum()
        ref_image, _, ref_depth, _ = ref
        ref_loss = (ref_image * cot_image).sum()
        if sums:
            loss = loss + (info.depth * cot_depth.to(device)).sum()
            ref_loss = ref_loss + (ref_depth * cot_depth).sum()
        loss.backward()
        ref_loss.backward()
        grads[chunk] = [t.grad.double().cpu() for t in tensors]
        for name, ours, theirs in zip(["means", "quats", "scales", "opacities", "sh"], grads[chunk], ref_tensors):
            expected = theirs.grad
            assert expected.abs().max() > 0, name
            torch.testing.assert_close(
                ours,
                expected,
                atol=VJP_REL[name] * expected.abs().max().item(),
                rtol=0,
                msg=lambda m, n=name: f"{n}: {m}",
            )
    ranges = info.tile_ranges.cpu()
    last = info.last_contributor.cpu()
    walks = [
        last[ty * 16 : ty * 16 + 16, tx * 16 : tx * 16 + 16].max().item() - ranges[ty * info.tiles_x + tx, 0].item() + 1
        for ty in range(info.tiles_y)
        for tx in range(info.tiles_x)
    ]
    assert max(walks) > 2 * 256, "the walks must span several chunks"
    for chunked, whole in zip(grads[256], grads[0]):
        torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-4 * whole.abs().max().item())


def test_absgrad_matches_reference(device):
    """The AbsGS accumulator equals the sum over pixels of |per-pixel gradient of the 2D mean|."""
    scene = make_scene(30, 32, 32, sh_degree=0, seed=6, hard_cases=False)
    weights = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(2))
    tensors = [t.to(device).requires_grad_() for t in scene.tensors()]
    image, _, info = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=32, height=32)
    info.retain_absgrad()
    (image * weights.to(device)).sum().backward()
    # Reference: per-pixel gradient of each pixel's loss term with respect to the 2D means.
    d = [t.double() for t in scene.tensors()]
    mean2d, conic, depths, opac, valid = reference.project(*d[:4], scene.viewmat.double(), scene.K.double(), 32, 32)
    mean2d = mean2d.detach().requires_grad_()
    colors = reference.sh_colors(d[0], d[4], 0, scene.viewmat.double())
    expected = torch.zeros(30, 2, dtype=torch.float64)
    order = torch.sort(depths, stable=True).indices
    order = order[valid[order]]
    for y in range(32):
        for x in range(32):
            delta = mean2d[order] - torch.tensor([x + 0.5, y + 0.5], dtype=torch.float64)
            power = -0.5 * torch.einsum("mi,mij,mj->m", delta, conic[order], delta)
            alpha = torch.clamp(opac[order] * torch.exp(power), max=0.99)
            alpha = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
            t_after = torch.cumprod(1 - alpha, 0)
            alpha = alpha * (t_after.detach() >= 1e-4)
            t_after = torch.cumprod(1 - alpha, 0)
            t_before = torch.cat([t_after.new_ones(1), t_after[:-1]])
            pixel = ((alpha * t_before) @ colors[order] * weights[y, x].double()).sum()
            (grad,) = torch.autograd.grad(pixel, mean2d, allow_unused=True)
            if grad is not None:
                expected += grad.abs()
    torch.testing.assert_close(
        info.means2d_absgrad.cpu().double(), expected, atol=1e-4 * expected.abs().max().item(), rtol=0
    )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="streams are a CUDA matter")
def test_kernels_run_on_torch_current_stream():
    """Under ``torch.cuda.stream(s)`` every Warp launch of the forward and backward pass goes to
    ``s`` (torch's kernels already do), and the result equals the default stream's."""
    import warp as wp

    scene = make_scene(200, 48, 32, sh_degree=2, seed=21)
    results, seen = [], []
    launch = wp.launch

    def recording_launch(*args, **kwargs):
        seen.append(wp.get_stream().cuda_stream)
        return launch(*args, **kwargs)

    side = torch.cuda.Stream()
    for stream in (torch.cuda.current_stream(), side):
        tensors = [t.cuda().requires_grad_() for t in scene.tensors()]
        torch.cuda.synchronize()
        seen.clear()
        wp.launch = recording_launch
        try:
            with torch.cuda.stream(stream):
                image, _, _ = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=48, height=32)
                image.square().sum().backward()
        finally:
            wp.launch = launch
        torch.cuda.synchronize()
        assert seen and set(seen) == {stream.cuda_stream}
        results.append([image.detach(), *(t.grad for t in tensors)])
    image_default, *grads_default = results[0]
    image_side, *grads_side = results[1]
    assert torch.equal(image_default, image_side)
    # The gradients are sums of float atomics, whose order varies from run to run: an entry that
    # cancels (a small sum of large terms) can differ by more than 1e-5 of itself.
    for a, b in zip(grads_default, grads_side):
        torch.testing.assert_close(a, b, atol=1e-5 * b.abs().max().item(), rtol=1e-5)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_sh_in_two_tensors_renders_and_differentiates_as_one(device, degree):
    """``rasterize(sh=dc, sh_rest=rest)`` (what the trainer passes: no concatenation) gives the
    image and the gradients of ``rasterize(sh=cat([dc, rest]))``, at degrees below the stored 3."""
    scene = make_scene(150, 40, 30, sh_degree=3, seed=21)
    means, quats, scales, opacities, sh = (t.to(device) for t in scene.tensors())
    camera = dict(viewmat=scene.viewmat, K=scene.K, width=40, height=30, sh_degree=degree)
    dc, rest = sh[:, :1].clone().requires_grad_(), sh[:, 1:].clone().requires_grad_()
    joined = sh.clone().requires_grad_()
    image_two, _, _ = cdcgs.rasterize(means, quats, scales, opacities, dc, sh_rest=rest, **camera)
    image_one, _, _ = cdcgs.rasterize(means, quats, scales, opacities, joined, **camera)
    weights = torch.rand(image_one.shape, generator=torch.Generator().manual_seed(2)).to(device)
    (image_two * weights).sum().backward()
    (image_one * weights).sum().backward()
    assert torch.equal(image_two, image_one)
    # On the CPU the same sums in the same order: bit-exact. On CUDA the gradients are sums of
    # float atomics whose order varies from run to run (an ulp or so apart).
    exact = device == "cpu"
    torch.testing.assert_close(
        torch.cat([dc.grad, rest.grad], dim=1), joined.grad, rtol=0 if exact else 1e-5, atol=0 if exact else 1e-6
    )
    assert (joined.grad[:, (degree + 1) ** 2 :] == 0).all() and joined.grad[:, 0].abs().max() > 0
    with pytest.raises(ValueError, match=r"sh must have shape \[150, 1, 3\], got \[150, 16, 3\]"):
        cdcgs.rasterize(means, quats, scales, opacities, sh, sh_rest=rest, **camera)
    with pytest.raises(ValueError, match="sh_rest needs sh"):
        cdcgs.rasterize(means, quats, scales, opacities, colors=sh[:, 0], sh_rest=rest, **camera)


def test_a_render_with_capacity_reads_nothing_and_checks_later(device, monkeypatch):
    """``capacity``: the pairs go into fixed slots and nothing is read back (the count reader is
    never called). With room, the image, alpha and gradients are those of the counted render and
    ``info.check()`` gives its count; one slot short, check() raises CapacityError with the count
    needed; NaN in an input is named by check(), not by the render."""
    from cdcgs.errors import CapacityError, NonFiniteError

    scene = make_scene(300, 61, 37, seed=4).to(device)
    weights = torch.rand(37, 61, 3, generator=torch.Generator().manual_seed(1)).to(device)

    def render(capacity=None, tensors=None):
        tensors = tensors or [t.clone().requires_grad_(True) for t in scene.tensors()]
        camera = {"viewmat": scene.viewmat, "K": scene.K, "width": scene.width, "height": scene.height}
        image, alpha, info = cdcgs.rasterize(*tensors, **camera, capacity=capacity)
        ((image * weights).sum() + alpha.sum()).backward()
        return image.detach(), alpha.detach(), [t.grad for t in tensors], info

    image, alpha, grads, info = render()
    count = info.num_intersections
    assert info.pending is None and info.check() == count > 0
    exact = device == "cpu"  # on CUDA the backward's atomic sums may add in another order
    monkeypatch.setattr(cdcgs.render, "_count_reader", lambda *a: pytest.fail("a render with capacity read the count"))
    for capacity in (count, 2 * count):
        image_c, alpha_c, grads_c, info_c = render(capacity)
        assert info_c.num_intersections == capacity and info_c.check() == count
        assert torch.equal(image_c, image) and torch.equal(alpha_c, alpha)
        for got, want in zip(grads_c, grads):
            torch.testing.assert_close(got, want, rtol=0 if exact else 1e-5, atol=0 if exact else 1e-6)
    *_, short = render(count - 1)
    with pytest.raises(CapacityError, match=f"has {count} .* more than the capacity {count - 1}") as raised:
        short.check()
    assert (raised.value.needed, raised.value.capacity) == (count, count - 1)
    tensors = [t.clone().requires_grad_(True) for t in scene.tensors()]
    with torch.no_grad():
        tensors[0][100, 1] = float("nan")  # a mean: the render without capacity would refuse it
    *_, poisoned = render(2 * count, tensors)
    with pytest.raises(NonFiniteError, match="means has non-finite values"):
        poisoned.check()
    for bad in (0, -3, 2.5, True, "100", cdcgs.render.MAX_CAPACITY + 1):
        with pytest.raises(ValueError, match="capacity must be a positive int"):
            cdcgs.rasterize(*scene.tensors(), viewmat=scene.viewmat, K=scene.K, width=61, height=37, capacity=bad)
    # The render's other forms: colours, a background tensor, the depth map; and a view of nothing.
    monkeypatch.undo()  # the counted renders to compare with read their counts
    camera = cdcgs.prepare_camera(scene.viewmat, scene.K, scene.width, scene.height)
    means, quats, scales, opacities, sh = scene.tensors()
    variants = {
        "colors": {"colors": sh[:, 0].clone()},
        "background": {"sh": sh, "background": torch.tensor([0.2, 0.5, 0.9], device=device)},
        "depth": {"sh": sh, "render_depth": True},
    }
    for name, extra in variants.items():
        counted = cdcgs.rasterize(means, quats, scales, opacities, camera=camera, **extra)
        slotted = cdcgs.rasterize(means, quats, scales, opacities, camera=camera, capacity=count + 5, **extra)
        assert torch.equal(slotted[0], counted[0]) and torch.equal(slotted[1], counted[1]), name
        if name == "depth":
            assert torch.equal(slotted[2].depth, counted[2].depth)
        assert slotted[2].check() == counted[2].num_intersections, name
    behind = means + torch.tensor([0.0, 0.0, -100.0], device=device) @ scene.viewmat[:3, :3].to(device)
    *_, nothing = cdcgs.rasterize(behind, quats, scales, opacities, sh, camera=camera, capacity=1)
    assert nothing.check() == 0
    if device.startswith("cuda"):  # torch is asked to fail on any synchronisation while it renders
        torch.cuda.set_sync_debug_mode("error")
        try:
            cdcgs.rasterize(means, quats, scales, opacities, sh, camera=camera, capacity=count)
        finally:
            torch.cuda.set_sync_debug_mode("default")
