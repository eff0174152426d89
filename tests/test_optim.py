"""FusedAdam (``--optimizer adam`` and ``selective``) against a float64 Adam written out here,
torch's Adam, the densification surgery and a training step; its kernel from plain Warp."""

import copy

import numpy as np
import pytest
import torch
import warp as wp
from helpers import SHORT, hand_model, tiny_config

import cdcgs.train.optim
from cdcgs.kernels import adam_quads, fused_adam_kernel, selective_adam_kernel
from cdcgs.train import ops
from cdcgs.train.config import LearningRates
from cdcgs.train.optim import FusedAdam
from cdcgs.train.trainer import Trainer

SHAPES = {"means": (3,), "opacity": (), "sh_rest": (15, 3)}


def reference_steps(params, grads, masks, lr, betas, eps):
    """float64: Adam with the group's step count t for every row, applied to the rows of each
    step's mask only (the others keep parameter and moments)."""
    b1, b2 = betas
    p = {k: v.double().clone() for k, v in params.items()}
    m = {k: torch.zeros_like(v) for k, v in p.items()}
    v = {k: torch.zeros_like(x) for k, x in p.items()}
    for t, (grad, mask) in enumerate(zip(grads, masks), start=1):
        for k in p:
            g = grad[k].double()
            rows = mask.view(-1, *[1] * (g.dim() - 1)).expand_as(g)
            new_m = b1 * m[k] + (1 - b1) * g
            new_v = b2 * v[k] + (1 - b2) * g * g
            step = lr / (1 - b1**t) * new_m / (new_v.sqrt() / (1 - b2**t) ** 0.5 + eps)
            m[k] = torch.where(rows, new_m, m[k])
            v[k] = torch.where(rows, new_v, v[k])
            p[k] = torch.where(rows, p[k] - step, p[k])
    return p, m, v


@pytest.mark.parametrize("share", [1.0, 0.4])
def test_selected_rows_follow_adam_the_others_stay(device, share):
    g = torch.Generator().manual_seed(3)
    n, lr, betas, eps = 37, 0.01, (0.9, 0.999), 1e-15
    params = {k: torch.randn(n, *shape, generator=g) for k, shape in SHAPES.items()}
    steps = 6
    grads = [
        {k: torch.randn(n, *shape, generator=g) * 10 ** (-k_ % 3) for k_, (k, shape) in enumerate(SHAPES.items())}
        for _ in range(steps)
    ]
    masks = [torch.rand(n, generator=g) < share for _ in range(steps)]
    masks[-1][:3] = False  # some rows are never selected at the end
    live = {k: v.clone().to(device).requires_grad_() for k, v in params.items()}
    optimizer = FusedAdam([{"params": [p]} for p in live.values()], lr=lr, betas=betas, eps=eps)
    for grad, mask in zip(grads, masks):
        for k, p in live.items():
            p.grad = grad[k].to(device)
        optimizer.step(mask.to(device))
    ref_p, ref_m, ref_v = reference_steps(params, grads, masks, lr, betas, eps)
    for k, p in live.items():
        state = optimizer.state[p]
        torch.testing.assert_close(p.detach().cpu().double(), ref_p[k], rtol=1e-5, atol=1e-6)
        # float32 against float64: an entry that cancels is off by an ulp of the largest term
        for ours, ref in ((state["exp_avg"], ref_m[k]), (state["exp_avg_sq"], ref_v[k])):
            torch.testing.assert_close(ours.cpu().double(), ref, rtol=1e-5, atol=1e-6 * ref.abs().max().item())
        assert float(state["step"]) == steps
    never = ~torch.stack(masks).any(dim=0)
    for k, p in live.items():
        assert torch.equal(p.detach().cpu()[never], params[k][never]), "an unselected row moved"


def test_without_a_mask_it_is_torch_adam(device):
    g = torch.Generator().manual_seed(4)
    a = torch.randn(50, 3, generator=g).to(device).requires_grad_()
    b = a.detach().clone().requires_grad_()
    ours = FusedAdam([a], lr=0.003, eps=1e-15)
    theirs = torch.optim.Adam([b], lr=0.003, eps=1e-15)
    for step in range(5):
        grad = torch.randn(50, 3, generator=g).to(device)
        a.grad, b.grad = grad.clone(), grad.clone()
        version = a._version
        ours.step()
        theirs.step()
        # Written through its address, yet torch sees the update as it sees its own Adam's: caches
        # keyed on the version (the trainer's Γ-pass scales and opacities) must not go stale.
        assert a._version > version, f"step {step}: FusedAdam left the parameter's version as it was"
    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(ours.state[a]["exp_avg_sq"], theirs.state[b]["exp_avg_sq"])


def test_a_gradient_scale_steps_the_scaled_gradients(device):
    """``gradient_scale`` s (the mean of a sum of two or three views' gradients, as the training on
    shards steps it): the float64 Adam of the gradients times s, parameters and moments, over five
    steps of gradients far from 1 (so that a rate scaled by s where it needs s^2 shows); the
    rates table's rows (``advance``) hold (1 - beta1) s and (1 - beta2) s^2, in double precision."""
    g = torch.Generator().manual_seed(9)
    lr, betas, eps = 0.01, (0.9, 0.999), 1e-15
    for scale in (0.5, 1.0 / 3.0):
        start = {"a": torch.randn(40, 3, generator=g), "b": torch.randn(40, generator=g)}
        params = {k: v.clone().to(device).requires_grad_() for k, v in start.items()}
        fused = FusedAdam(list(params.values()), lr=lr, betas=betas, eps=eps)
        grads = []
        for _ in range(5):
            grad = {k: 40.0 * torch.randn(v.shape, generator=g) for k, v in start.items()}
            grads.append({k: v * scale for k, v in grad.items()})
            for k, p in params.items():
                p.grad = grad[k].to(device)
            fused.step(gradient_scale=scale)
        everywhere = [torch.ones(40, dtype=torch.bool)] * 5
        p64, m64, v64 = reference_steps(start, grads, everywhere, lr, betas, eps)
        for k, p in params.items():
            torch.testing.assert_close(p.detach().cpu().double(), p64[k], rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(fused.state[p]["exp_avg"].cpu().double(), m64[k], rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(fused.state[p]["exp_avg_sq"].cpu().double(), v64[k], rtol=1e-5, atol=1e-5)
    rows = FusedAdam([torch.zeros(2, 3, requires_grad=True)], betas=(0.9, 0.99))
    rows.state[rows.param_groups[0]["params"][0]]["step"] = torch.tensor(0.0)
    rows.state[rows.param_groups[0]["params"][0]].update(exp_avg=torch.zeros(2, 3), exp_avg_sq=torch.zeros(2, 3))
    (row,) = rows.advance(rows.param_groups[0]["params"], gradient_scale=0.25)
    assert row[3] == pytest.approx(0.025, rel=1e-12) and row[4] == pytest.approx(0.000625, rel=1e-12)


# A 3DGS model's parameters: rows of 3, 3, 4, 1 (a 1-D tensor), 1 x 3 and 15 x 3 values.
MODEL_SHAPES = [(3,), (3,), (4,), (), (1, 3), (15, 3)]


def test_every_group_in_one_launch_is_torch_adam(device, monkeypatch):
    """Six groups, each with its own rate, eps and betas, one of them resumed at step 4: one
    launch per step, and every group where torch's Adam (the plain loop, as reference) puts it."""
    launches = []
    real_launch = cdcgs.train.optim.launch
    monkeypatch.setattr(cdcgs.train.optim, "launch", lambda *a, **k: launches.append(a[0]) or real_launch(*a, **k))
    g = torch.Generator().manual_seed(5)
    n = 23
    ours = [torch.randn(n, *shape, generator=g).to(device).requires_grad_() for shape in MODEL_SHAPES]
    theirs = [p.detach().clone().requires_grad_() for p in ours]
    settings = [
        {"lr": 0.01 * (k + 1), "eps": 10.0 ** -(8 + k), "betas": (0.9 - 0.05 * k, 0.999 - 0.001 * k)}
        for k in range(len(ours))
    ]
    fused = FusedAdam([{"params": [p], **s} for p, s in zip(ours, settings)])
    reference = torch.optim.Adam([{"params": [p], **s} for p, s in zip(theirs, settings)], foreach=False)
    earlier = torch.randn(n, *MODEL_SHAPES[2], generator=g).to(device)  # a group resumed after 4 steps
    for optimizer, p in ((fused, ours[2]), (reference, theirs[2])):
        optimizer.state[p] = {
            "step": torch.tensor(4.0),
            "exp_avg": earlier.clone() * 0.1,
            "exp_avg_sq": earlier.clone() ** 2 * 0.01,
        }
    for _ in range(5):
        for a, b in zip(ours, theirs):
            grad = torch.randn(a.shape, generator=g).to(device)
            a.grad, b.grad = grad.clone(), grad.clone()
        fused.step()
        reference.step()
    assert launches == [fused_adam_kernel] * 5
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        for key in ("exp_avg", "exp_avg_sq"):  # torch lerps the first moment: an ulp of the largest term apart
            ref = reference.state[b][key]
            torch.testing.assert_close(fused.state[a][key], ref, rtol=1e-5, atol=1e-6 * ref.abs().max().item())
    assert float(fused.state[ours[2]]["step"]) == 9 and float(fused.state[ours[0]]["step"]) == 5


def test_the_fused_kernel_from_plain_warp(device):
    """``fused_adam_kernel`` launched with Warp arrays and its two tables, no torch: two
    parameters of different widths, a row mask, against Adam in float64 written out with numpy.
    A thread updates a quad of four values: the second parameter starts at the first's quad count,
    and the launch is the sum of both parameters' quads."""
    wp_device = device  # "cpu" or "cuda", as Warp names them
    rng = np.random.default_rng(6)
    rows, widths, lrs, step = 11, (3, 5), (0.02, 0.5), 3
    values = [rng.normal(size=rows * w).astype(np.float32) for w in widths]
    grads = [rng.normal(size=rows * w).astype(np.float32) for w in widths]
    m0 = [rng.normal(size=rows * w).astype(np.float32) * 0.1 for w in widths]
    v0 = [(rng.normal(size=rows * w) ** 2).astype(np.float32) * 0.01 for w in widths]
    selected = (rng.random(rows) < 0.6).astype(np.uint8)
    arrays = [[wp.array(x[k], dtype=float, device=wp_device) for x in (values, grads, m0, v0)] for k in range(2)]
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    bc1, bc2 = 1 - beta1**step, 1 - beta2**step
    counts = [rows * w for w in widths]
    layout = [[0, counts[0], widths[0]], [adam_quads(counts[0]), counts[1], widths[1]]]
    dim = adam_quads(counts[0]) + adam_quads(counts[1])
    table = [[a.ptr for a in arrays[k]] + layout[k] for k in range(2)]
    parameters = wp.array(table, dtype=wp.int64, device=wp_device)
    rates = wp.array(
        [[lr, beta1, beta2, 1 - beta1, 1 - beta2, eps, bc1, np.sqrt(bc2)] for lr in lrs], dtype=float, device=wp_device
    )
    mask = wp.array(selected, dtype=wp.uint8, device=wp_device)
    never = wp.empty(0, dtype=wp.int32, device=wp_device)  # halt: empty, never halted
    halt = wp.ones(1, dtype=wp.int32, device=wp_device)
    wp.launch(fused_adam_kernel, dim, inputs=[parameters, rates, mask, halt], device=wp_device)
    assert np.array_equal(arrays[0][0].numpy(), values[0]), "a set halt changes nothing"
    wp.launch(fused_adam_kernel, dim, inputs=[parameters, rates, mask, never], device=wp_device)
    for k, w in enumerate(widths):
        g = grads[k].astype(np.float64)
        m = beta1 * m0[k] + (1 - beta1) * g
        v = beta2 * v0[k].astype(np.float64) + (1 - beta2) * g * g
        p = values[k] - lrs[k] / bc1 * m / (np.sqrt(v) / np.sqrt(bc2) + eps)
        keep = np.repeat(selected == 0, w)
        expected = [np.where(keep, values[k], p), np.where(keep, m0[k], m), np.where(keep, v0[k], v)]
        got = [arrays[k][0].numpy(), arrays[k][2].numpy(), arrays[k][3].numpy()]
        for ours, ref in zip(got, expected):
            np.testing.assert_allclose(ours, ref, rtol=2e-6, atol=1e-7)
        assert np.array_equal(got[0][keep], values[k][keep]), "an unselected row moved"


SENTINEL = -7.0  # the floats around each array: the kernel must leave them alone


@pytest.mark.parametrize("masked", [False, True])
def test_the_fused_kernel_on_tails_unaligned_arrays_and_rows_across_quads(device, masked):
    """Five parameters in one launch of ``fused_adam_kernel``: counts that are not multiples of
    four (a last, partial quad), rows of 3 and 5 values (quads that span two rows, each row
    selected on its own), and arrays that start 4, 8 or 12 bytes into larger ones (not 16-byte
    aligned: the quads go value by value), against Adam in float64 (numpy) and, bit for bit,
    ``selective_adam_kernel`` (one value a thread, ``adam_update`` as well). The floats around each
    array stay as they were. The 128-bit path (CUDA, no mask, aligned whole quads) is taken by the
    CUDA run only: on the CPU every quad goes value by value."""
    rng = np.random.default_rng(7)
    rows, pad, step = 13, 4, 4
    # (values per row, each array's offset in floats: value, gradient, exp_avg, exp_avg_sq)
    layouts = [(3, (0, 0, 0, 0)), (5, (0, 0, 0, 0)), (4, (0, 1, 0, 0)), (4, (0, 0, 0, 3)), (1, (2, 2, 2, 2))]
    lrs = [0.01 * (k + 1) for k in range(len(layouts))]
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    bc1, bc2 = 1 - beta1**step, 1 - beta2**step
    selected = (rng.random(rows) < 0.5).astype(np.uint8) if masked else np.ones(rows, dtype=np.uint8)
    host = []  # per parameter: value, gradient, exp_avg, exp_avg_sq (float32)
    for width, _ in layouts:
        n = rows * width
        moments = rng.normal(size=n) * 0.1, rng.normal(size=n) ** 2 * 0.01
        host.append([x.astype(np.float32) for x in (rng.normal(size=n), rng.normal(size=n), *moments)])

    def placed():
        """Each array inside a larger Warp array, at its offset, SENTINEL around it: (larger, view)."""
        out = []
        for (_, offsets), arrays in zip(layouts, host):
            pairs = []
            for x, offset in zip(arrays, offsets):
                larger = np.full(offset + x.size + pad, SENTINEL, dtype=np.float32)
                larger[offset : offset + x.size] = x
                larger = wp.array(larger, dtype=float, device=device)
                pairs.append((larger, larger[offset : offset + x.size]))
            out.append(pairs)
        return out

    fused, single = placed(), placed()
    assert (fused[2][1][1].ptr % 16, fused[4][0][1].ptr % 16) == (4, 8), "the offsets leave them unaligned"
    table, start = [], 0
    for (width, _), pairs in zip(layouts, fused):
        table.append([view.ptr for _, view in pairs] + [start, rows * width, width])
        start += adam_quads(rows * width)
    rates = [[lr, beta1, beta2, 1 - beta1, 1 - beta2, eps, bc1, np.sqrt(bc2)] for lr in lrs]
    mask = wp.array(selected, dtype=wp.uint8, device=device)
    inputs = [
        wp.array(table, dtype=wp.int64, device=device),
        wp.array(rates, dtype=float, device=device),
        mask if masked else wp.empty(0, dtype=wp.uint8, device=device),
        wp.empty(0, dtype=wp.int32, device=device),
    ]
    wp.launch(fused_adam_kernel, start, inputs=inputs, device=device)
    for (width, _), pairs, lr in zip(layouts, single, lrs):
        arrays = [view for _, view in pairs]
        arguments = [*arrays, mask, width, lr, beta1, beta2, 1 - beta1, 1 - beta2, eps, bc1, np.sqrt(bc2)]
        wp.launch(selective_adam_kernel, rows * width, inputs=arguments, device=device)
    for k, (width, offsets) in enumerate(layouts):
        value, grad, m0, v0 = (x.astype(np.float64) for x in host[k])
        m = beta1 * m0 + (1 - beta1) * grad
        v = beta2 * v0 + (1 - beta2) * grad * grad
        p = value - lrs[k] / bc1 * m / (np.sqrt(v) / np.sqrt(bc2) + eps)
        keep = np.repeat(selected == 0, width)
        expected = {0: np.where(keep, value, p), 2: np.where(keep, m0, m), 3: np.where(keep, v0, v)}
        for j, reference in expected.items():  # the gradient (1) is read only
            got = fused[k][j][1].numpy()
            np.testing.assert_allclose(got, reference, rtol=2e-6, atol=1e-7, err_msg=f"parameter {k}, array {j}")
            assert np.array_equal(got, single[k][j][1].numpy()), (
                f"parameter {k}, array {j}: not selective_adam_kernel's"
            )
        for j, (larger, view) in enumerate(fused[k]):
            around = np.delete(larger.numpy(), np.arange(offsets[j], offsets[j] + view.shape[0]))
            assert np.all(around == SENTINEL), f"parameter {k}, array {j}: a float outside it changed"


@pytest.mark.parametrize(
    "mask, message",
    [
        (torch.ones(9, dtype=torch.bool), r"selected must be a bool \[10\] mask .* got torch.bool \[9\]"),
        (torch.ones(10), r"selected must be a bool \[9\] mask .* got torch.float32 \[10\]"),
    ],
)
def test_a_bad_mask_is_refused_and_nothing_moves(mask, message):
    first = torch.randn(9, 2, requires_grad=True)  # a mask fits this group but not the next one
    p = torch.randn(10, 3, requires_grad=True)
    before = [first.detach().clone(), p.detach().clone()]
    first.grad, p.grad = torch.ones(9, 2), torch.ones(10, 3)
    optimizer = FusedAdam([{"params": [first]}, {"params": [p]}], lr=0.1)
    with pytest.raises(ValueError, match=message):
        optimizer.step(mask)
    assert torch.equal(first.detach(), before[0]) and torch.equal(p.detach(), before[1])
    assert not optimizer.state, "no state was created either"


@pytest.mark.parametrize("kind", ["selective", "torch-adam"])
def test_the_surgery_keeps_its_moments_in_step(kind):
    """Removing Gaussians under FusedAdam (selective) and torch's Adam, each loaded from a state
    of the other kind: each parameter's moments keep their rows, and the next step counts on from
    the loaded one (selective: the unselected rows keep their moments)."""
    model, adam = hand_model()
    optimizer = ops.make_optimizer(model, LearningRates(), 1.0, kind)
    assert isinstance(optimizer, FusedAdam) == (kind == "selective")
    ops.load_optimizer_state(optimizer, adam.state_dict())  # as a resume with the other optimizer loads it
    for group in optimizer.param_groups:
        group["lr"] = 0.01  # the hand model's Adam leaves the opacity rate unset
    before = {g["name"]: optimizer.state[g["params"][0]]["exp_avg"].clone() for g in optimizer.param_groups}
    drop = torch.zeros(model.num, dtype=torch.bool)
    drop[[1, 4]] = True
    ops.remove(model, optimizer, drop)
    for group in optimizer.param_groups:
        p = group["params"][0]
        assert model.params[group["name"]] is p
        torch.testing.assert_close(optimizer.state[p]["exp_avg"], before[group["name"]][~drop])
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    if kind == "selective":
        optimizer.step(torch.arange(model.num) % 2 == 0)
    else:
        optimizer.step()
    for group in optimizer.param_groups:
        state = optimizer.state[group["params"][0]]
        assert float(state["step"]) == 2.0  # loaded 1, one step
        kept = before[group["name"]][~drop]
        if kind == "selective":
            torch.testing.assert_close(state["exp_avg"][1::2], kept[1::2])
        else:
            torch.testing.assert_close(state["exp_avg"], 0.9 * kept + 0.1)


def test_a_training_step_moves_only_what_the_view_sees(tiny_scene, tmp_path):
    trainer = Trainer(tiny_config(tiny_scene, tmp_path, iters=30, optimizer="selective"), SHORT)
    trainer._setup()
    for _ in range(3):
        trainer.train_step()
    seen = []
    render = trainer._render

    def spy(*args, **kwargs):
        out = render(*args, **kwargs)
        seen.append(out[2].visible.clone())
        return out

    trainer._render = spy
    before = {k: p.detach().clone() for k, p in trainer.model.params.items()}
    trainer.train_step()
    visible = seen[-1]
    assert 0 < visible.sum() < visible.numel(), "the test needs Gaussians on both sides"
    for k, p in trainer.model.params.items():
        assert torch.equal(p.detach()[~visible], before[k][~visible]), f"{k}: an unseen Gaussian moved"
    assert not torch.equal(trainer.model.params["means"].detach()[visible], before["means"][visible])


def test_a_bad_state_is_refused_and_nothing_moves():
    """The kernel writes the moments through their addresses: a state of the wrong shape, dtype or
    layout (a broken or foreign checkpoint) is refused before anything is updated."""
    first = torch.randn(6, 3, requires_grad=True)
    p = torch.randn(4, 3, requires_grad=True)
    first.grad, p.grad = torch.ones(6, 3), torch.ones(4, 3)
    for bad, message in (
        ({"exp_avg": torch.zeros(2, 3)}, r"'exp_avg' of a \[4, 3\] parameter .* got torch.float32 \[2, 3\]"),
        ({"exp_avg_sq": torch.zeros(4, 3, dtype=torch.float64)}, r"'exp_avg_sq' .* got torch.float64 \[4, 3\]"),
        ({"exp_avg": torch.zeros(3, 4).t()}, r"'exp_avg' .* not contiguous"),
        ({"step": None}, r"no step count"),
    ):
        optimizer = FusedAdam([{"params": [first]}, {"params": [p]}], lr=0.1)
        state = {"step": torch.tensor(2.0), "exp_avg": torch.zeros(4, 3), "exp_avg_sq": torch.zeros(4, 3)}
        state.update(bad)
        if state["step"] is None:
            del state["step"]
        optimizer.state[p] = state
        before = [first.detach().clone(), p.detach().clone()]
        with pytest.raises(ValueError, match=message):
            optimizer.step()
        assert torch.equal(first.detach(), before[0]) and torch.equal(p.detach(), before[1])
        assert first not in optimizer.state, "the first parameter's state was not created either"


def test_a_torch_adam_checkpoint_resumes():
    """A state saved by torch's Adam (step on the device for its fused flavour, its own options in
    the groups) goes on as torch's Adam would, a parameter without a gradient skipped; options
    FusedAdam does not have are refused."""
    g = torch.Generator().manual_seed(7)
    ours = [torch.randn(9, *shape, generator=g).requires_grad_() for shape in MODEL_SHAPES[:3]]
    theirs = [p.detach().clone().requires_grad_() for p in ours]
    reference = torch.optim.Adam([{"params": [p], "lr": 0.01 * (k + 1)} for k, p in enumerate(theirs)], eps=1e-15)
    fused = FusedAdam([{"params": [p], "lr": 0.01 * (k + 1)} for k, p in enumerate(ours)], eps=1e-15)
    grads = [[torch.randn(p.shape, generator=g) for p in ours] for _ in range(5)]
    for step in range(5):
        if step == 3:
            fused.load_state_dict(copy.deepcopy(reference.state_dict()))  # a checkpoint: its own tensors
            for p_ours, p_theirs in zip(ours, theirs):
                p_ours.data.copy_(p_theirs.detach())
        for k, (a, b) in enumerate(zip(ours, theirs)):
            skip = step == 4 and k == 1  # no gradient for this parameter at this step
            a.grad = None if skip else grads[step][k].clone()
            b.grad = None if skip else grads[step][k].clone()
        if step >= 3:
            fused.step()
        reference.step()
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    assert float(fused.state[ours[1]]["step"]) == 4 and float(fused.state[ours[0]]["step"]) == 5
    fused.param_groups[0]["amsgrad"] = True
    with pytest.raises(ValueError, match="FusedAdam is Adam without amsgrad"):
        fused.step()


def test_a_model_too_large_for_one_launch_takes_several(monkeypatch):
    """Launch indices are 32-bit: above MAX_LAUNCH_THREADS threads (quads of four values) the
    parameters go into several launches, with the same result."""
    g = torch.Generator().manual_seed(8)
    base = [torch.randn(10, *shape, generator=g) for shape in MODEL_SHAPES]
    grads = [torch.randn(p.shape, generator=g) for p in base]
    launches = []
    real_launch = cdcgs.train.optim.launch
    monkeypatch.setattr(cdcgs.train.optim, "launch", lambda *a, **k: launches.append(a[1]) or real_launch(*a, **k))
    results = {}
    for limit in (cdcgs.train.optim.MAX_LAUNCH_THREADS, 120):
        monkeypatch.setattr(cdcgs.train.optim, "MAX_LAUNCH_THREADS", limit)
        launches.clear()
        params = [p.clone().requires_grad_() for p in base]
        optimizer = FusedAdam([{"params": [p], "lr": 0.05} for p in params])
        for p, grad in zip(params, grads):
            p.grad = grad.clone()
        optimizer.step(torch.arange(10) % 3 != 0)
        results[limit] = (list(launches), [p.detach() for p in params])
    one, several = results.values()
    # 30, 30, 40, 10, 30 and 450 values: 8, 8, 10, 3, 8 and 113 quads
    assert one[0] == [150] and several[0] == [37, 113], "sizes of the launches: all 150 quads, then split"
    for a, b in zip(one[1], several[1]):
        assert torch.equal(a, b)


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"lr": None}, "a learning rate >= 0 for every group, got None"),
        ({"lr": -0.1}, "a learning rate >= 0"),
        ({"eps": -1e-8}, "eps >= 0"),
        ({"betas": (0.9, 1.0)}, r"two betas in \[0, 1\)"),
    ],
)
def test_bad_rates_are_refused_before_any_state_changes(setting, message):
    """A group's rate left unset (as set_hyperparameters leaves the opacity rate for its caller) or
    out of range is refused before a state is created or a step counted: the next step's bias
    correction would otherwise be off."""
    first = torch.randn(5, 3, requires_grad=True)
    p = torch.randn(5, 2, requires_grad=True)
    first.grad, p.grad = torch.ones(5, 3), torch.ones(5, 2)
    optimizer = FusedAdam([{"params": [first]}, {"params": [p]}], lr=0.1)
    optimizer.param_groups[1].update(setting)
    with pytest.raises(ValueError, match=message):
        optimizer.step()
    assert not optimizer.state, "no state was created, no step counted"


def test_torch_adam_option_trains_as_fused_adam(tiny_scene, tmp_path):
    """``--optimizer torch-adam`` (torch's fused Adam, the reference FusedAdam replaced) and the
    default ``adam`` move a training the same way, up to float32 rounding."""
    params = {}
    for kind in ("adam", "torch-adam"):
        trainer = Trainer(tiny_config(tiny_scene, tmp_path / kind, iters=30, optimizer=kind), SHORT)
        trainer._setup()
        for _ in range(4):
            trainer.train_step()
        params[kind] = {k: p.detach().clone() for k, p in trainer.model.params.items()}
        if kind == "torch-adam":  # fused on CUDA, torch's loop on the CPU
            assert type(trainer.optimizer) is torch.optim.Adam
            fused = True if trainer.device.type == "cuda" else None
            assert all(group["fused"] is fused for group in trainer.optimizer.param_groups)
        else:
            assert isinstance(trainer.optimizer, FusedAdam)
    start = Trainer(tiny_config(tiny_scene, tmp_path / "start", iters=30), SHORT)
    start._setup()
    for k, p in params["adam"].items():
        moved = (p - start.model.params[k].detach()).abs().max()
        assert moved > 0 or k == "sh_rest", f"{k} did not move"  # sh_rest waits for degree 1
        # Both are Adam in float32 with eps 1e-15: where a gradient is near zero, m / sqrt(v) is
        # ill-conditioned and the two roundings of the first moment (torch lerps it) part by up to
        # about 0.4% of the largest move (one quaternion entry here), everywhere else by ~1e-4.
        torch.testing.assert_close(params["torch-adam"][k], p, rtol=1e-4, atol=1e-2 * float(moved))


@pytest.mark.parametrize("saved, loaded", [("adam", "torch-adam"), ("torch-adam", "adam")])
def test_a_checkpoint_resumes_with_the_other_adam(saved, loaded):
    """A state saved by one Adam goes on in the other as the saver would have gone on: the loaded
    optimizer keeps its own implementation flags (torch's ``fused``), not the saver's."""
    g = torch.Generator().manual_seed(9)
    model, _ = hand_model(8)
    rates = LearningRates(opacity_logits=0.025)
    first = ops.make_optimizer(model, rates, 1.0, saved)
    grads = [{k: torch.randn(p.shape, generator=g) for k, p in model.params.items()} for _ in range(4)]
    for step in range(2):
        for k, p in model.params.items():
            p.grad = grads[step][k].clone()
        first.step()
    state = copy.deepcopy(first.state_dict())
    twin = {k: p.detach().clone().requires_grad_() for k, p in model.params.items()}
    second = ops.make_optimizer(hand_model(8)[0], rates, 1.0, loaded)
    for group in second.param_groups:  # the second optimizer on its own copies of the parameters
        group["params"][0] = twin[group["name"]]
    ops.load_optimizer_state(second, state)
    ops.set_hyperparameters(second, rates, 1.0)  # as a resumed run does: the command's rates
    own = type(second) is torch.optim.Adam
    assert all(("fused" in group) == own for group in second.param_groups)
    assert not own or all(group["fused"] is None for group in second.param_groups)  # its own, on the CPU
    for step in (2, 3):
        for k in model.params:
            model.params[k].grad = grads[step][k].clone()
            twin[k].grad = grads[step][k].clone()
        first.step()
        second.step()
    for k, p in model.params.items():
        torch.testing.assert_close(twin[k], p.detach(), rtol=1e-5, atol=1e-6)
        assert float(second.state[twin[k]]["step"]) == 4


def test_a_fused_torch_adam_keeps_its_flag_and_finds_its_step_counts_on_the_device():
    """``load_optimizer_state`` into torch's fused Adam from a FusedAdam state: a plain
    ``load_state_dict`` would take the saver's groups and leave ``fused`` unset (torch's slow
    loop); the loader keeps ``fused`` True and puts each step count on its parameter's device."""
    if not hasattr(torch, "_fused_adam_"):
        pytest.skip("this torch has no fused Adam")
    model, _ = hand_model(8)
    saver = ops.make_optimizer(model, LearningRates(opacity_logits=0.025), 1.0, "adam")
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    saver.step()
    groups = [{"params": [p], "name": name} for name, p in model.params.items()]
    try:
        fused = torch.optim.Adam(groups, lr=0.01, eps=1e-15, fused=True)
    except RuntimeError:
        pytest.skip("this torch has no fused Adam on the CPU")
    plain = copy.deepcopy(fused)
    plain.load_state_dict(copy.deepcopy(saver.state_dict()))
    assert not any(group["fused"] for group in plain.param_groups), "torch's own load drops the flag"
    ops.load_optimizer_state(fused, copy.deepcopy(saver.state_dict()))
    for group in fused.param_groups:
        p = group["params"][0]
        assert group["fused"] is True and fused.state[p]["step"].device == p.device
        assert fused.state[p]["step"].dtype == torch.float32 and float(fused.state[p]["step"]) == 1.0
    fused.step()  # goes on from step 1


def test_the_gamma_pass_sees_the_scales_and_opacities_after_an_adam_step(tiny_scene, tmp_path):
    """The trainer computes a Γ pass's scales and opacities once and keeps them until a parameter
    changes, which it learns from torch's version counters: FusedAdam's update, written by a
    kernel, must count as a change (before, the next pass saw the scales of the pass before)."""
    trainer = Trainer(tiny_config(tiny_scene, tmp_path / "run"))
    trainer._setup()
    trainer._bins(0).finish()
    for p in trainer.model.params.values():
        p.grad = torch.ones_like(p)
    trainer.optimizer.step()
    trainer._bins(0).finish()
    torch.testing.assert_close(trainer._shape["scales"], trainer.model.scales().detach(), rtol=0, atol=0)
    torch.testing.assert_close(trainer._shape["opacities"], trainer.model.opacities().detach(), rtol=0, atol=0)
