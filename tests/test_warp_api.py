"""The kernels work from plain Warp, without torch, as the README shows."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

import cdcgs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "examples"))
import warp_launch  # noqa: E402  (examples/ is put on the path just above)

PUBLIC_KERNEL_API = {
    "TILE_SIZE",
    "BLOCK_SIZE",
    "AdamStep",
    "Camera",
    "make_camera",
    "project_gaussians_kernel",
    "sh_to_color_kernel",
    "sh_to_color_backward_kernel",
    "sh_to_color_grouped_backward_kernel",
    "sh_to_color_staged_backward_kernel",
    "SH_BLOCK",
    "bin_gaussians",
    "TileBins",
    "blend_forward_kernel",
    "blend_backward_kernel",
    "blend_backward_lean_kernel",
    "complexity_kernel",
    "complexity_views_kernel",
    "knn_search",
    "ssim_l1_forward_rows_kernel",
    "ssim_l1_forward_kernel",
    "ssim_l1_backward_rows_kernel",
    "ssim_l1_backward_kernel",
    "ssim_l1_launch_size",
    "selective_adam_kernel",
    "fused_adam_kernel",
    "adam_quads",
    "mcmc_noise_kernel",
}


def test_kernels_do_not_import_torch():
    code = "import sys, cdcgs.kernels; assert 'torch' not in sys.modules, 'cdcgs.kernels imported torch'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_kernel_package_exports_what_a_launch_needs():
    """``cdcgs.kernels`` exports exactly what a ``wp.launch`` user needs; the binning internals
    stay in their module, and the submodules stay importable under their own names."""
    import importlib

    import cdcgs.kernels as kernels

    assert set(kernels.__all__) == PUBLIC_KERNEL_API and len(kernels.__all__) == len(PUBLIC_KERNEL_API)
    for name in kernels.__all__:
        assert getattr(kernels, name) is not None, name
    from cdcgs.kernels.binning import count_tiles_kernel, emit_keys_kernel, gather_counts_kernel, tile_ranges_kernel

    assert all(k is not None for k in (count_tiles_kernel, emit_keys_kernel, gather_counts_kernel, tile_ranges_kernel))
    # `knn_search` does not shadow the submodule `knn` (a function named `knn` would).
    knn_module = importlib.import_module("cdcgs.kernels.knn")
    assert kernels.knn is knn_module and knn_module.knn_search is kernels.knn_search
    assert kernels.BLOCK_SIZE == kernels.TILE_SIZE * kernels.TILE_SIZE


def test_importing_cdcgs_leaves_warp_uninitialised(device):
    """Warp's runtime starts on first use (a render), not when cdcgs or its kernels are imported."""
    code = f"""
import warp as wp
calls = []
real_init = wp.init
wp.init = lambda: (calls.append(1), real_init())[1]
import cdcgs, cdcgs.kernels, cdcgs.render, cdcgs.neighbors, cdcgs.complexity
assert not calls, "importing cdcgs called wp.init()"
import torch
gaussian = [torch.tensor(v, device="{device}") for v in ([[0.0, 0.0, 3.0]], [[1.0, 0.0, 0.0, 0.0]], [[0.1, 0.1, 0.1]], [1.0])]
K = [[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]
_, alpha, _ = cdcgs.rasterize(*gaussian, colors=torch.ones(1, 3, device="{device}"), viewmat=torch.eye(4), K=K, width=8, height=8)
assert calls, "rendering did not initialise Warp"
assert alpha.max() > 0.5
"""
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_plain_warp_launch_matches_rasterize(device):
    means, quats, scales, opacities, sh, viewmat, K, width, height = warp_launch.demo_scene(n=300)
    image = warp_launch.render(means, quats, scales, opacities, sh, viewmat, K, width, height, device=device)
    t = lambda a: torch.from_numpy(a).to(device)
    expected, _, _ = cdcgs.rasterize(
        t(means),
        t(quats),
        t(scales),
        t(opacities),
        t(sh),
        viewmat=viewmat,
        K=K,
        width=width,
        height=height,
        background=[1.0, 1.0, 1.0],
    )
    assert image.shape == (height, width, 3)
    assert (image < 0.99).any(), "the demo scene must not be empty"
    np.testing.assert_allclose(image, expected.cpu().numpy(), atol=1e-6)


def test_generated_sh_adjoint_equals_the_written_out_one(device):
    """``wp.Tape`` users get Warp's generated adjoint of ``sh_to_color_kernel``; ``rasterize`` uses
    ``sh_to_color_backward_kernel``. Both must give the same gradients at every degree, and both
    skip the Gaussians the radii mark culled (colour 0, gradient 0)."""
    import warp as wp

    from cdcgs.kernels import sh_to_color_backward_kernel, sh_to_color_kernel
    from cdcgs.kernels.adam import AdamStep

    rng = np.random.default_rng(0)
    n = 64
    for degree in range(4):
        means = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
        sh = wp.array(0.3 * rng.normal(size=(n, 16, 3)).astype(np.float32), dtype=wp.vec3, device=device)
        grad_colors = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
        center = wp.vec3(0.1, -0.2, 3.0)
        culled = np.arange(n) % 5 == 0
        radii = wp.array(
            np.repeat(np.where(culled, 0, 3)[:, None], 2, axis=1).astype(np.int32), dtype=wp.vec2i, device=device
        )
        colors = wp.empty(n, dtype=wp.vec3, device=device)
        wp.launch(
            sh_to_color_kernel,
            n,
            inputs=[means, sh, None, degree, center, None, radii],
            outputs=[colors, None],
            device=device,
        )
        assert (colors.numpy()[culled] == 0).all() and (colors.numpy()[~culled] > 0).any()
        generated = wp.zeros(n, dtype=wp.vec3, device=device), wp.zeros((n, 16), dtype=wp.vec3, device=device)
        wp.launch(
            sh_to_color_kernel,
            n,
            inputs=[means, sh, None, degree, center, None, radii],
            outputs=[colors, None],
            adj_inputs=[*generated, None, 0, wp.vec3(), None, None],
            adj_outputs=[grad_colors, None],
            adjoint=True,
            device=device,
        )
        written = wp.empty(n, dtype=wp.vec3, device=device), wp.empty((n, 16), dtype=wp.vec3, device=device)
        wp.launch(
            sh_to_color_backward_kernel,
            n,
            inputs=[means, sh, None, degree, center, None, radii, colors, grad_colors, AdamStep(), AdamStep()],
            outputs=[*written, None],
            device=device,
        )
        for name, ours, theirs in zip(("means", "sh"), written, generated):
            assert np.abs(theirs.numpy()).max() > 0 or (
                name == "means" and degree == 0
            )  # degree 0 ignores the direction
            assert (ours.numpy()[culled] == 0).all()
            np.testing.assert_allclose(ours.numpy(), theirs.numpy(), atol=1e-5, rtol=1e-4)


def test_grouped_sh_adjoint_equals_the_per_gaussian_one(device):
    """On CUDA ``rasterize`` runs the SH adjoint with 16 threads per Gaussian (half-warp sums), or
    with the coefficients staged in shared memory (``SH_BACKWARD_CUDA = "staged"``, two arrays only);
    each must give what the per-Gaussian kernel gives, at every degree, with as many coefficients
    stored as the degree needs or all 16, with culled Gaussians and a last block that is not full."""
    if device != "cuda":
        pytest.skip("the grouped SH adjoint uses warp shuffles: CUDA only")
    import warp as wp

    from cdcgs.kernels import sh_to_color_backward_kernel, sh_to_color_grouped_backward_kernel, sh_to_color_kernel
    from cdcgs.kernels._constants import MAX_SH_COEFFICIENTS
    from cdcgs.kernels.adam import AdamStep
    from cdcgs.kernels.projection import SH_BLOCK, sh_to_color_staged_backward_kernel

    rng = np.random.default_rng(1)
    n = 2 * SH_BLOCK + 33  # the last warp holds one Gaussian, the last block 33
    culled = np.arange(n) % 7 == 3
    radii = wp.array(
        np.repeat(np.where(culled, 0, 2)[:, None], 2, axis=1).astype(np.int32), dtype=wp.vec2i, device=device
    )
    for degree in range(4):
        for stored in sorted({(degree + 1) ** 2, 16}):
            means = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
            coefficients = 0.3 * rng.normal(size=(n, stored, 3)).astype(np.float32)
            coefficients[::4, 0, 1] = -6.0  # these green channels clamp at 0: their gradient is cut
            sh = wp.array(coefficients, dtype=wp.vec3, device=device)
            grad_colors = wp.array(rng.normal(size=(n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
            center = wp.vec3(0.1, -0.2, 3.0)
            colors = wp.empty(n, dtype=wp.vec3, device=device)
            wp.launch(
                sh_to_color_kernel,
                n,
                inputs=[means, sh, None, degree, center, None, radii],
                outputs=[colors, None],
                device=device,
            )
            clamped = (np.arange(n) % 4 == 0) & ~culled
            assert (colors.numpy()[clamped, 1] == 0).all() and (colors.numpy()[~culled] > 0).any()
            outputs = {}
            for name, backward, dim in (
                ("per gaussian", sh_to_color_backward_kernel, n),
                ("grouped", sh_to_color_grouped_backward_kernel, MAX_SH_COEFFICIENTS * n),
            ):
                grads = wp.full(n, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                grad_sh = wp.full((n, stored), wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                inputs = [means, sh, None, degree, center, None, radii, colors, grad_colors, AdamStep(), AdamStep()]
                wp.launch(backward, dim, inputs=inputs, outputs=[grads, grad_sh, None], device=device)
                outputs[name] = (grads.numpy(), grad_sh.numpy())
                if stored > 1:  # the same with the coefficients in two arrays, degree 0 apart
                    dc = wp.array(coefficients[:, :1].copy(), dtype=wp.vec3, device=device)
                    rest = wp.array(coefficients[:, 1:].copy(), dtype=wp.vec3, device=device)
                    grads = wp.full(n, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                    grad_dc = wp.full((n, 1), wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                    grad_rest = wp.full((n, stored - 1), wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                    inputs = [means, dc, rest, degree, center, None, radii, colors, grad_colors, AdamStep(), AdamStep()]
                    wp.launch(backward, dim, inputs=inputs, outputs=[grads, grad_dc, grad_rest], device=device)
                    both = np.concatenate([grad_dc.numpy(), grad_rest.numpy()], axis=1)
                    outputs[name + " split"] = (grads.numpy(), both)
            if stored > 1:  # the staged kernel: flat higher coefficients, a launch of whole blocks
                dc = wp.array(coefficients[:, :1].copy(), dtype=wp.vec3, device=device)
                rest = wp.array(coefficients[:, 1:].reshape(-1).copy(), dtype=float, device=device)
                grads = wp.full(n, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                grad_dc = wp.full((n, 1), wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=device)
                grad_rest = wp.full(n * (stored - 1) * 3, 7.0, dtype=float, device=device)
                wp.launch(
                    sh_to_color_staged_backward_kernel,
                    -(-n // SH_BLOCK) * SH_BLOCK,
                    inputs=[means, dc, rest, degree, center, None, radii, colors, grad_colors, AdamStep(), AdamStep()],
                    outputs=[grads, grad_dc, grad_rest],
                    block_dim=SH_BLOCK,
                    device=device,
                )
                both = np.concatenate([grad_dc.numpy(), grad_rest.numpy().reshape(n, stored - 1, 3)], axis=1)
                outputs["staged split"] = (grads.numpy(), both)
            for ours, theirs in zip(outputs["grouped"], outputs["per gaussian"]):
                assert (theirs != 7.0).all()  # every entry written
                np.testing.assert_allclose(ours, theirs, atol=1e-5, rtol=1e-4)
            for name in ("grouped split", "per gaussian split", "staged split"):
                for ours, theirs in zip(outputs.get(name, ()), outputs["per gaussian"]):
                    assert (ours != 7.0).all()
                    np.testing.assert_allclose(ours, theirs, atol=1e-5, rtol=1e-4)


def test_lean_blend_adjoint_equals_the_full_one(device):
    """``blend_backward_lean_kernel`` (what ``rasterize`` runs when neither the depth sum nor the
    AbsGS sums are wanted) gives the full adjoint's gradients for means, conics, colours and
    opacities, and leaves the depth and AbsGS outputs alone."""
    import warp as wp
    from conftest import make_scene

    from cdcgs.kernels import BLOCK_SIZE, blend_backward_kernel, blend_backward_lean_kernel

    scene = make_scene(80, 40, 24, sh_degree=1, seed=4, hard_cases=False)
    tensors = [t.to(device) for t in scene.tensors()]
    _, _, info = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=40, height=24)
    h, w = 24, 40
    arr = lambda t, dtype: wp.from_torch(t.detach().contiguous(), dtype=dtype)
    rng = torch.Generator().manual_seed(5)
    grad_image, grad_alpha = torch.randn(h, w, 3, generator=rng).to(device), torch.randn(h, w, generator=rng).to(device)
    inputs = [
        arr(info.tile_ranges, wp.int32),
        arr(info.sorted_gauss_ids, wp.int32),
        arr(info.means2d, wp.vec2),
        arr(info.conics, wp.vec3),
        arr(info.colors, wp.vec3),
        arr(info.opacities, wp.float32),
        arr(info.depths, wp.float32),
        wp.array([wp.vec3(0.2, 0.3, 0.4)], dtype=wp.vec3, device=device),
        w,
        h,
        info.tiles_x,
        0,  # one block per tile: no chunk table, no checkpoints (the four None below)
        None,
        arr(info.transmittance, wp.float32),
        arr(info.last_contributor, wp.int32),
        None,
        None,
        None,
        None,
        arr(grad_image, wp.vec3),
        arr(grad_alpha, wp.float32),
        wp.zeros((h, w), dtype=float, device=device),
    ]
    n = info.means2d.shape[0]
    results = {}
    for name, kernel in (("full", blend_backward_kernel), ("lean", blend_backward_lean_kernel)):
        outputs = [wp.zeros(n, dtype=t, device=device) for t in (wp.vec2, wp.vec3, wp.vec3, float)]
        outputs += [
            wp.full(n, 7.0, dtype=float, device=device),
            wp.full(n, wp.vec2(7.0, 7.0), dtype=wp.vec2, device=device),
        ]
        dim = info.tiles_x * info.tiles_y * BLOCK_SIZE
        wp.launch(kernel, dim, inputs=inputs, outputs=outputs, block_dim=BLOCK_SIZE, device=device)
        results[name] = [o.numpy() for o in outputs]
    for full, lean in zip(results["full"][:4], results["lean"][:4]):
        assert np.abs(full).max() > 0
        np.testing.assert_allclose(lean, full, atol=1e-6 * np.abs(full).max(), rtol=1e-5)
    assert (results["lean"][4] == 7.0).all() and (results["lean"][5] == 7.0).all()
    assert (results["full"][5] != 7.0).any()


def test_launch_arguments_do_not_keep_tensors_alive():
    """``_interop.wp_arg`` caches descriptors by address; a cached descriptor must not pin its tensor
    (every tensor ever rendered would stay allocated, and autograd would copy gradients it could take)."""
    import gc
    import weakref

    import warp as wp

    from cdcgs._interop import wp_arg

    tensor = torch.zeros(10, 3)
    first = wp_arg(tensor, wp.vec3)
    assert wp_arg(tensor, wp.vec3) is first  # cached
    alive = weakref.ref(tensor)
    del tensor
    gc.collect()
    assert alive() is None


def test_warp_still_pins_tensors_where_unpin_descriptor_looks():
    """``_interop.unpin_descriptor`` clears two private attributes of what
    ``wp.from_torch(..., return_ctype=True)`` returns (the one use of Warp internals in cdcgs). This
    fails when Warp stops keeping the tensor there: then the descriptor would pin it some other way
    and the cache would leak, or the code has nothing left to clear."""
    import gc
    import weakref

    import warp as wp

    from cdcgs._interop import unpin_descriptor

    wp.init()
    tensor = torch.zeros(10, 3)
    grad = torch.zeros(10, 3)
    descriptor = wp.from_torch(tensor, dtype=wp.vec3, grad=grad, return_ctype=True)
    assert descriptor._ref is tensor and descriptor._gradref is grad  # Warp pins both here
    alive, grad_alive = weakref.ref(tensor), weakref.ref(grad)
    del tensor, grad
    gc.collect()
    assert alive() is not None and grad_alive() is not None  # pinned: kept alive by the descriptor
    unpin_descriptor(descriptor)
    gc.collect()
    assert alive() is None and grad_alive() is None  # the descriptor was the last reference

    class Foreign:
        pass

    with pytest.raises(RuntimeError, match="_ref/_gradref"):
        unpin_descriptor(Foreign())


def test_warp_array_views_keep_their_tensor_and_hand_it_back(device):
    """``_interop.wp_array`` views a tensor's memory as Warp sees it (``wp.from_torch``'s shape and
    values), keeps the tensor alive as long as the view, and ``torch_tensor`` hands back that very
    tensor; what it cannot view (strides, a wrong inner size or dtype) it refuses."""
    import gc
    import weakref

    import warp as wp

    from cdcgs._interop import torch_tensor, wp_array

    for tensor, dtype in [
        (torch.arange(12, dtype=torch.float32, device=device).view(4, 3), wp.vec3),
        (torch.arange(8, dtype=torch.int32, device=device).view(4, 2), wp.vec2i),
        (torch.arange(6, dtype=torch.float32, device=device).view(2, 3), wp.float32),
        (torch.zeros(0, dtype=torch.int32, device=device), wp.int32),
    ]:
        view, reference = wp_array(tensor, dtype), wp.from_torch(tensor, dtype=dtype)
        assert view.shape == reference.shape and view.dtype == reference.dtype and view.ptr == reference.ptr
        np.testing.assert_array_equal(view.numpy(), reference.numpy())
        assert torch_tensor(view) is tensor
    sliced = wp_array(torch.arange(5, dtype=torch.int32, device=device), wp.int32)[:3]
    assert torch_tensor(sliced).tolist() == [0, 1, 2]  # another Warp array: wp.to_torch's view
    tensor = torch.zeros(10, 3, device=device)
    alive = weakref.ref(tensor)
    view = wp_array(tensor, wp.vec3)
    del tensor
    gc.collect()
    assert alive() is not None, "the view must keep its tensor alive"
    del view
    gc.collect()
    assert alive() is None
    for tensor, dtype in [
        (torch.zeros(4, 6, device=device)[:, :3], wp.vec3),
        (torch.zeros(4, 2, device=device), wp.vec3),
        (torch.zeros(4, 3, dtype=torch.float64, device=device), wp.vec3),
    ]:
        with pytest.raises(ValueError, match="views a contiguous"):
            wp_array(tensor, dtype)


def test_recorded_launches_run_each_call_with_its_own_arguments(device):
    """``_interop.launch`` records a kernel's first launch and replays the record: every later call
    runs with its own launch size, arrays and numbers (a replay that kept any of an earlier call's
    would flag the wrong input, or miss one), as ``wp.launch`` runs it, and no record keeps an
    array's memory alive."""
    import gc
    import weakref

    import warp as wp

    from cdcgs._interop import launch, warp_scope, wp_arg, wp_array
    from cdcgs.kernels._checks import find_nonfinite_kernel

    rng = np.random.default_rng(7)

    def check(threads, bad, in_place=None):
        """Flags of six inputs where those in ``bad`` hold one NaN, by ``launch`` and by ``wp.launch``."""
        values = [torch.tensor(rng.normal(size=int(rng.integers(5, 40))), dtype=torch.float32) for _ in range(6)]
        values = in_place or [v.to(device) for v in values]
        for k, v in enumerate(values):
            v.copy_(torch.randn(v.shape[0], device=device))
            if k in bad:
                v[-1] = float("nan")  # the last value: reached by the last thread's stride only
        flags = [torch.zeros(6, dtype=torch.int32, device=device) for _ in range(2)]
        with warp_scope(torch.device(device)):
            # one input as a Warp array (held as its descriptor), the others as cached descriptors
            arguments = [wp_array(values[0], wp.float32), *(wp_arg(v, wp.float32) for v in values[1:]), threads]
            launch(find_nonfinite_kernel, threads, inputs=arguments, outputs=[wp_arg(flags[0], wp.int32)])
            wp.launch(find_nonfinite_kernel, threads, inputs=arguments, outputs=[wp_arg(flags[1], wp.int32)])
        assert flags[0].tolist() == flags[1].tolist() == [int(k in bad) for k in range(6)], (threads, bad)
        return values

    check(3, {2})  # recorded
    check(1, {4})  # replayed: other arrays, launch size and thread count
    kept = check(64, {0, 5})
    check(64, {1}, in_place=kept)  # the same arrays again, their values changed
    with warp_scope(torch.device(device)):  # an empty launch runs nothing and records nothing
        launch(find_nonfinite_kernel, 0, inputs=[wp_arg(kept[0], wp.float32)] * 6 + [0], outputs=[None])
    tensor = torch.zeros(10, device=device)
    alive = weakref.ref(tensor)
    with warp_scope(torch.device(device)):
        flags = torch.zeros(6, dtype=torch.int32, device=device)
        launch(
            find_nonfinite_kernel, 2, inputs=[wp_array(tensor, wp.float32)] * 6 + [2], outputs=[wp_arg(flags, wp.int32)]
        )
    del tensor
    gc.collect()
    assert alive() is None, "a recorded launch kept its Warp array's tensor alive"


@pytest.mark.parametrize("threads", [1, 3, 64])
def test_nonfinite_check_strides_over_every_value(device, threads):
    """Each thread of ``find_nonfinite_kernel`` walks its share of every input; whatever the launch
    size, exactly the inputs holding a NaN or an infinity are flagged (numpy decides)."""
    import warp as wp

    from cdcgs.kernels._checks import find_nonfinite_kernel

    rng = np.random.default_rng(4)
    for trial in range(6):
        inputs = [rng.normal(size=int(rng.integers(1, 50))).astype(np.float32) for _ in range(6)]
        for values in inputs:
            if rng.random() < 0.5:
                values[rng.integers(len(values))] = rng.choice([np.nan, np.inf, -np.inf])
        flags = wp.zeros(6, dtype=wp.int32, device=device)
        arrays = [wp.array(v, dtype=wp.float32, device=device) for v in inputs]
        wp.launch(find_nonfinite_kernel, threads, inputs=[*arrays, threads], outputs=[flags], device=device)
        expected = [int(not np.isfinite(v).all()) for v in inputs]
        assert flags.numpy().tolist() == expected, trial


def test_projection_writes_every_entry_and_flags_nonfinite_inputs(device):
    """``project_gaussians_kernel`` overwrites every output entry (zeros for culled Gaussians, so
    callers need no zero fill) and, given an int32 [4], flags exactly the inputs holding a NaN or
    an infinity (numpy decides); a shorter flag array is never written past its end."""
    import warp as wp

    from cdcgs.kernels import make_camera, project_gaussians_kernel

    means, quats, scales, opacities, _, viewmat, K, width, height = warp_launch.demo_scene(n=200)
    means[:20, 2] = -9.0  # behind the camera (it sits at z = -4 looking down +z)
    opacities[20:30] = 0.002  # too transparent to reach 1/255
    camera = make_camera(viewmat, K, width, height)
    n = len(means)
    specs = [
        (wp.vec2, 2, np.float32),
        (wp.vec3, 3, np.float32),
        (float, 1, np.float32),
        (float, 1, np.float32),
        (wp.vec2i, 2, np.int32),
    ]

    def project(inputs, fill, flags=None):
        outputs = [
            wp.array(np.full((n, k) if k > 1 else n, fill, dtype=npt), dtype=dt, device=device) for dt, k, npt in specs
        ]
        arrays = [wp.array(a, dtype=dt, device=device) for a, dt in zip(inputs, (wp.vec3, wp.vec4, wp.vec3, float))]
        wp.launch(
            project_gaussians_kernel, n, inputs=[*arrays, camera, None, 0], outputs=[*outputs, flags], device=device
        )
        return [o.numpy() for o in outputs]

    zero_filled = project((means, quats, scales, opacities), 0)
    garbage_filled = project((means, quats, scales, opacities), 7)
    culled = (zero_filled[4] == 0).all(axis=1)
    assert culled[:30].all() and (~culled).sum() > 100
    for a, b in zip(zero_filled, garbage_filled):
        np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(6)
    for trial in range(8):
        inputs = [a.copy() for a in (means, quats, scales, opacities)]
        for values in inputs:
            if rng.random() < 0.5:
                values.reshape(-1)[rng.integers(values.size)] = rng.choice([np.nan, np.inf, -np.inf])
        flags = wp.zeros(4, dtype=wp.int32, device=device)
        project(inputs, 0, flags)
        expected = [int(not np.isfinite(v).all()) for v in inputs]
        assert flags.numpy().tolist() == expected, trial
        # A shorter array: its last entry takes the inputs beyond it, nothing is written past it.
        padded = wp.zeros(4, dtype=wp.int32, device=device)
        project(inputs, 0, padded[:2])
        assert padded.numpy().tolist() == [expected[0], max(expected[1:]), 0, 0], trial


def test_mcmc_noise_kernel_from_warp_arrays_alone(device):
    """The kernel as a ``wp.launch`` user runs it, on Warp arrays: each mean moves by
    R diag(s²) Rᵀ z · sigmoid(-k (o - t)) · scale, against numpy in float64 (the rotation from
    the quaternion written out, as 3DGS's code builds it)."""
    import numpy as np
    import warp as wp

    from cdcgs.kernels import mcmc_noise_kernel

    rng = np.random.default_rng(3)
    n = 7
    quats = rng.normal(size=(n, 4)) * 2.0  # not unit: the kernel normalises
    log_scales = rng.normal(-3.0, 0.5, size=(n, 3))
    logits = np.array([-7.0, -5.3, -4.0, -2.0, 0.0, 2.0, 6.0])  # opacities from 0.0009 to 0.998
    z = rng.normal(size=(n, 3))
    means = rng.normal(size=(n, 3))
    k, t, scale = 100.0, 0.005, 5e5 * 1.6e-4
    arrays = [
        wp.array(a.astype(np.float32), dtype=d, device=device)
        for a, d in ((quats, wp.vec4), (log_scales, wp.vec3), (logits, wp.float32), (z, wp.vec3))
    ]
    never = wp.empty(0, dtype=wp.int32, device=device)  # halt: empty, never halted
    noise = wp.zeros(n, dtype=wp.vec3, device=device)  # out: zeros, to get the noise itself
    wp.launch(mcmc_noise_kernel, n, inputs=[*arrays, k, t, scale, never], outputs=[noise], device=device)
    moved = wp.array(means.astype(np.float32), dtype=wp.vec3, device=device)  # out: the means
    wp.launch(mcmc_noise_kernel, n, inputs=[*arrays, k, t, scale, never], outputs=[moved], device=device)
    halted = wp.array(means.astype(np.float32), dtype=wp.vec3, device=device)
    halt = wp.ones(1, dtype=wp.int32, device=device)
    wp.launch(mcmc_noise_kernel, n, inputs=[*arrays, k, t, scale, halt], outputs=[halted], device=device)
    assert np.array_equal(halted.numpy(), means.astype(np.float32)), "a set halt changes nothing"
    expected = np.zeros((n, 3))
    for i in range(n):
        w, x, y, c = quats[i] / np.linalg.norm(quats[i])
        r = np.array(
            [
                [1 - 2 * (y * y + c * c), 2 * (x * y - w * c), 2 * (x * c + w * y)],
                [2 * (x * y + w * c), 1 - 2 * (x * x + c * c), 2 * (y * c - w * x)],
                [2 * (x * c - w * y), 2 * (y * c + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        opacity = 1 / (1 + np.exp(-logits[i]))
        gate = 1 / (1 + np.exp(k * (opacity - t)))
        expected[i] += r @ np.diag(np.exp(2 * log_scales[i])) @ r.T @ z[i] * gate * scale
    np.testing.assert_allclose(noise.numpy(), expected, rtol=2e-4, atol=1e-12)
    assert np.abs(noise.numpy()[-1]).max() < 1e-30 < np.abs(noise.numpy()[0]).max()  # the opaque one stays put
    np.testing.assert_allclose(moved.numpy(), means + expected, rtol=0, atol=1e-6)  # added in place


def test_a_scope_under_another_torch_stream_launches_on_that_stream(device):
    """``warp_scope`` nested in one for the same device: on the outer scope's stream while torch's
    current stream is the same, on the new one inside ``torch.cuda.stream`` (a caller that runs
    cdcgs functions on a stream of its own), and back on the outer one after; a launch there runs
    on it (CUDA only: the CPU has no streams)."""
    if device != "cuda":
        pytest.skip("CUDA streams")
    import warp as wp

    from cdcgs._interop import launch, warp_scope, wp_arg
    from cdcgs.kernels._checks import find_nonfinite_kernel

    device = torch.device("cuda")
    side = torch.cuda.Stream(device=device)
    values = torch.zeros(1 << 20, device=device)
    values[-1] = float("nan")
    flags = torch.zeros(6, dtype=torch.int32, device=device)
    side.wait_stream(torch.cuda.current_stream(device))  # the inputs above are written on the current stream
    with warp_scope(device):
        outer = wp.get_stream().cuda_stream
        assert outer == torch.cuda.current_stream(device).cuda_stream
        with warp_scope(device):
            assert wp.get_stream().cuda_stream == outer
        with torch.cuda.stream(side), warp_scope(device):
            assert wp.get_stream().cuda_stream == side.cuda_stream
            torch.cuda._sleep(200_000_000)  # about 0.1 s of the side stream: the launch queues behind it
            launch(
                find_nonfinite_kernel,
                64,
                inputs=[wp_arg(values, wp.float32)] * 6 + [64],
                outputs=[wp_arg(flags, wp.int32)],
            )
        assert wp.get_stream().cuda_stream == outer
    # Read on the caller's stream, which does not wait for the side one: still unset, so the
    # launch went to the side stream (on the caller's, the read would have waited for it).
    assert flags.tolist() == [0] * 6
    side.synchronize()
    assert flags.tolist() == [1] * 6
