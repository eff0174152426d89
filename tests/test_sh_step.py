"""An Adam step of the SH coefficients applied by the render's adjoint (``rasterize(sh_step=...)``,
what a replayed training step of one view does): the step that FusedAdam and torch's Adam take
with the gradients the adjoint would have returned, the other gradients unchanged, nothing while
halted, and a bad step refused before anything moves."""

import math

import pytest
import torch
from conftest import make_scene

import cdcgs.render
from cdcgs.render import ShAdamStep, prepare_camera, rasterize, sh_adjoint
from cdcgs.train.optim import FusedAdam

LR = {"sh": 0.0025, "sh_rest": 0.0025 / 20}


def split_scene(device, degree: int):
    """A scene with culled and clamped Gaussians, its coefficients as a trainer keeps them (degree 0
    apart from the 15 others), every tensor a leaf on ``device``."""
    scene = make_scene(160, 40, 28, sh_degree=3, seed=5, hard_cases=True)
    means, quats, scales, opacities, sh = (t.to(device) for t in scene.tensors())
    tensors = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "sh": sh[:, :1].contiguous(),
        "sh_rest": sh[:, 1:].contiguous(),
    }
    return scene, {k: v.detach().clone().requires_grad_() for k, v in tensors.items()}, degree


def render_loss(scene, leaves, degree, sh_step=None):
    image, _, info = rasterize(
        leaves["means"],
        leaves["quats"],
        leaves["scales"],
        leaves["opacities"],
        leaves["sh"],
        sh_rest=leaves["sh_rest"],
        sh_degree=degree,
        viewmat=scene.viewmat,
        K=scene.K,
        width=40,
        height=28,
        sh_step=sh_step,
    )
    weights = torch.linspace(-1.0, 2.0, image.numel(), device=image.device).view_as(image)
    return (image * weights).sum(), info


def optimizer_with_history(leaves, generator) -> FusedAdam:
    """FusedAdam over sh and sh_rest, three steps in (moments of random size, step count 3), so
    that the bias corrections and both moments take part."""
    optimizer = FusedAdam([{"params": [leaves[k]], "lr": LR[k]} for k in ("sh", "sh_rest")], eps=1e-15)
    for name in ("sh", "sh_rest"):
        p = leaves[name]
        optimizer.state[p] = {
            "step": torch.tensor(3.0),
            "exp_avg": (1e-3 * torch.randn(p.shape, generator=generator)).to(p.device),
            "exp_avg_sq": (1e-6 * torch.rand(p.shape, generator=generator)).to(p.device),
        }
    return optimizer


def step_of(optimizer, leaves, halt=None, selective=False) -> ShAdamStep:
    params = [leaves["sh"], leaves["sh_rest"]]
    rates = torch.tensor(optimizer.advance(params), dtype=torch.float32).to(params[0].device)
    moments = [(optimizer.state[p]["exp_avg"], optimizer.state[p]["exp_avg_sq"]) for p in params]
    return ShAdamStep(rates, (0, 1), moments[0], moments[1], halt, selective)


def copy_of(leaves):
    return {k: v.detach().clone().requires_grad_() for k, v in leaves.items()}


def optimizer_state_before(name, leaves, key="exp_avg"):
    """The moment ``key`` that ``optimizer_with_history`` gives ``name`` (seed 7), before any step."""
    fresh = copy_of(leaves)
    return optimizer_with_history(fresh, torch.Generator().manual_seed(7)).state[fresh[name]][key]


def adam64(p, g, m, v, lr, step, beta1=0.9, beta2=0.999, eps=1e-15):
    """Adam's step ``step`` in float64 from float32 inputs: (value, bound) for the new value and
    both moments, each bound 16 float32 roundings of the magnitudes that enter it (the terms of a
    moment, not its value, which may cancel; for the value the step's error through m, v, the
    division and the root)."""
    p, g, m, v = (t.double() for t in (p, g, m, v))
    u = 16 * 2.0**-24
    m_bound = u * ((beta1 * m).abs() + ((1 - beta1) * g).abs())
    m = beta1 * m + (1 - beta1) * g
    v = beta2 * v + (1 - beta2) * g * g
    v_bound = u * v
    denominator = v.sqrt() / math.sqrt(1 - beta2**step) + eps
    update = lr / (1 - beta1**step) * m / denominator
    p_bound = u * (p.abs() + update.abs()) + (lr / (1 - beta1**step)) * m_bound / denominator
    p_bound = p_bound + update.abs() * v_bound / v.clamp_min(1e-30)
    tiny = 1e-30  # keeps a zero bound (all terms zero) from dividing by zero
    return [(p - update, p_bound + tiny), (m, m_bound + tiny), (v, v_bound + tiny)]


def torch_adam_step(leaves, grads, optimizer):
    """torch's Adam (an independent reference) from ``optimizer``'s state, on copies."""
    copies = {k: leaves[k].detach().clone().requires_grad_() for k in ("sh", "sh_rest")}
    adam = torch.optim.Adam([{"params": [copies[k]], "lr": LR[k]} for k in ("sh", "sh_rest")], eps=1e-15, foreach=False)
    for k in ("sh", "sh_rest"):
        copies[k].grad = grads[k].clone()
        adam.state[copies[k]] = {key: value.clone() for key, value in optimizer.state[leaves[k]].items()}
    adam.step()
    return copies


@pytest.mark.parametrize("selective", [False, True], ids=["adam", "selective"])
@pytest.mark.parametrize("kernel", ["staged", "grouped"])
@pytest.mark.parametrize("degree", [1, 3])
def test_the_adjoints_step_is_adams_step_with_its_gradients(device, degree, kernel, selective, monkeypatch):
    """The SH adjoint with a step, against the adjoint's gradients given to FusedAdam (bit for bit
    on the CPU; on CUDA to the few ulps of the SH kernels' fast-math division and root) and to
    torch's Adam: every coefficient moves, those of culled Gaussians and of bands above the degree
    by their momentum alone; the means' gradient is the same. Selective: FusedAdam with the view's
    visible Gaussians as its mask, the others untouched."""
    if kernel == "grouped" and device != "cuda":
        pytest.skip("the CPU runs one SH adjoint; the grouped and staged ones are CUDA's")
    monkeypatch.setattr(cdcgs.render, "SH_BACKWARD_CUDA", kernel)
    scene, leaves, degree = split_scene(device, degree)
    with torch.no_grad():
        _, info = render_loss(scene, leaves, degree)
    radii, colors = info.radii, info.colors.detach()
    assert (radii[:, 0] <= 0).any() and (colors == 0).any(), "culled Gaussians and clamped colours"
    camera = prepare_camera(scene.viewmat, scene.K, 40, 28)
    grad_colors = torch.randn(colors.shape, generator=torch.Generator().manual_seed(9)).to(device)
    means = leaves["means"].detach()

    def adjoint(coefficients, step=None):
        return sh_adjoint(
            means, coefficients["sh"], coefficients["sh_rest"], degree, camera, radii, colors, grad_colors, step
        )

    separate = copy_of(leaves)
    separate_adam = optimizer_with_history(separate, torch.Generator().manual_seed(7))
    grad_means, grad_sh, grad_rest = adjoint(separate)
    assert (grad_rest[:, (degree + 1) ** 2 - 1 :] == 0).all() and (grad_sh[radii[:, 0] <= 0] == 0).all()
    reference = torch_adam_step(separate, {"sh": grad_sh, "sh_rest": grad_rest}, separate_adam)
    separate["sh"].grad, separate["sh_rest"].grad = grad_sh, grad_rest
    visible = info.visible
    separate_adam.step(visible if selective else None)

    fused = copy_of(leaves)
    fused_adam = optimizer_with_history(fused, torch.Generator().manual_seed(7))
    not_halted = torch.zeros(1, dtype=torch.int32, device=device)
    with torch.no_grad():
        fused_means, none_sh, none_rest = adjoint(fused, step_of(fused_adam, fused, not_halted, selective))
    assert none_sh is None and none_rest is None
    assert torch.equal(fused_means, grad_means)
    grads = {"sh": grad_sh, "sh_rest": grad_rest}
    for name in ("sh", "sh_rest"):
        ours, theirs = fused_adam.state[fused[name]], separate_adam.state[separate[name]]
        stepped = visible if selective else torch.ones_like(visible)
        if device == "cpu":
            assert torch.equal(fused[name], separate[name]), name
            for key in ("exp_avg", "exp_avg_sq"):
                assert torch.equal(ours[key], theirs[key]), (name, key)
        # Both against a float64 Adam step from the same float32 inputs, to bounds from the terms'
        # magnitudes: on CUDA the SH kernels' fast math divides and takes roots to a few ulps, and
        # either kernel may fuse a multiply into an add, which moves a moment that cancels (b1 m
        # against (1 - b1) g) by an ulp of its terms, not of its value.
        before = optimizer_state_before(name, leaves, "exp_avg"), optimizer_state_before(name, leaves, "exp_avg_sq")
        expected = adam64(leaves[name].detach(), grads[name], *before, LR[name], step=4)
        for param, state in ((fused[name], ours), (separate[name], theirs)):
            values = (param, state["exp_avg"], state["exp_avg_sq"])
            for got, (value, bound), what in zip(values, expected, ("value", "exp_avg", "exp_avg_sq")):
                error = (got.double() - value).abs()[stepped]
                worst = (error / bound[stepped]).max().item()
                assert worst <= 1.0, f"{name} {what}: {worst:.2f} of the float64 bound"
        moved = (fused[name][stepped] != leaves[name][stepped]).double().mean()  # (a momentum near 0 may not move it)
        assert moved > 0.95, f"{1 - moved:.0%} of {name} did not move"
        culled = radii[:, 0] <= 0
        if selective:  # the Gaussians the view does not see keep their values and moments
            assert torch.equal(fused[name][~visible], leaves[name][~visible])
            assert torch.equal(ours["exp_avg"][~visible], optimizer_state_before(name, leaves)[~visible])
        else:
            assert (fused[name][culled] != leaves[name][culled]).double().mean() > 0.95, f"culled {name} did not move"
            torch.testing.assert_close(fused[name], reference[name], rtol=1e-6, atol=1e-7)


def test_a_render_with_a_step_takes_it_in_its_backward_pass(device):
    """Through ``rasterize``: the backward pass updates the coefficients and their moments as
    FusedAdam would with the render's gradients, gives them no gradient, and the other parameters
    the same gradients (on CUDA as close as two renders' atomics allow)."""
    scene, leaves, degree = split_scene(device, 3)
    separate = copy_of(leaves)
    separate_adam = optimizer_with_history(separate, torch.Generator().manual_seed(7))
    loss, _ = render_loss(scene, separate, degree)
    loss.backward()
    separate_adam.step()
    fused = copy_of(leaves)
    fused_adam = optimizer_with_history(fused, torch.Generator().manual_seed(7))
    loss, _ = render_loss(scene, fused, degree, step_of(fused_adam, fused))
    loss.backward()
    assert fused["sh"].grad is None and fused["sh_rest"].grad is None
    cpu = device == "cpu"  # on CUDA the blend adjoint's float atomics add in another order each render
    for name in ("means", "quats", "scales", "opacities"):
        torch.testing.assert_close(fused[name].grad, separate[name].grad, **close(cpu, 1e-4, 1e-5))
    for name in ("sh", "sh_rest"):
        torch.testing.assert_close(fused[name], separate[name], **close(cpu, 1e-6, 1e-7))
        ours, theirs = fused_adam.state[fused[name]], separate_adam.state[separate[name]]
        torch.testing.assert_close(ours["exp_avg"], theirs["exp_avg"], **close(cpu, 1e-4, 1e-12))
        torch.testing.assert_close(ours["exp_avg_sq"], theirs["exp_avg_sq"], **close(cpu, 1e-4, 1e-18))
        assert not torch.equal(fused[name], leaves[name])


def close(cpu: bool, rtol: float, atol: float) -> dict:
    """Bit for bit on the CPU, else these tolerances."""
    return {"rtol": 0.0, "atol": 0.0} if cpu else {"rtol": rtol, "atol": atol}


def test_a_halted_step_changes_nothing(device):
    scene, leaves, degree = split_scene(device, 3)
    fused = copy_of(leaves)
    adam = optimizer_with_history(fused, torch.Generator().manual_seed(3))
    before = {k: v.clone() for k, v in adam.state[fused["sh_rest"]].items()}
    halt = torch.ones(1, dtype=torch.int32, device=device)
    before_dc = {k: v.clone() for k, v in adam.state[fused["sh"]].items()}
    loss, _ = render_loss(scene, fused, degree, step_of(adam, fused, halt))
    loss.backward()
    assert torch.equal(fused["sh"], leaves["sh"]) and torch.equal(fused["sh_rest"], leaves["sh_rest"])
    for name, saved in (("sh_rest", before), ("sh", before_dc)):
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(adam.state[fused[name]][key], saved[key]), (name, key)
    assert fused["means"].grad is not None and fused["sh"].grad is None


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda s, leaves: ShAdamStep(s.rates, (0, 2), s.sh_moments, s.rest_moments), "rows"),
        (lambda s, leaves: ShAdamStep(s.rates[:, :7], s.rows, s.sh_moments, s.rest_moments), "rates"),
        (
            lambda s, leaves: ShAdamStep(s.rates, s.rows, s.sh_moments, (s.rest_moments[0][:, :3], s.rest_moments[1])),
            "moments of sh_rest",
        ),
        (lambda s, leaves: ShAdamStep(s.rates, s.rows, s.sh_moments, s.rest_moments, torch.ones(1)), "halt"),
        (lambda s, leaves: "adam", "ShAdamStep"),
    ],
    ids=["row", "rates", "moment", "halt", "type"],
)
def test_a_bad_step_is_refused_before_anything_moves(change, message):
    scene, leaves, degree = split_scene("cpu", 3)
    fused = copy_of(leaves)
    adam = optimizer_with_history(fused, torch.Generator().manual_seed(3))
    bad = change(step_of(adam, fused), fused)
    with pytest.raises(ValueError, match=message):
        render_loss(scene, fused, degree, bad)
    assert torch.equal(fused["sh_rest"], leaves["sh_rest"])


def test_a_step_refuses_coefficients_it_could_only_update_a_copy_of():
    """A non-contiguous ``sh_rest`` would be checked into a copy, which the step would update
    instead: refused, nothing moves."""
    scene, leaves, degree = split_scene("cpu", 3)
    wide = torch.zeros(leaves["sh_rest"].shape[0], 15, 6)
    wide[..., ::2] = leaves["sh_rest"].detach()
    strided = wide[..., ::2].requires_grad_()
    assert not strided.is_contiguous()
    leaves = {**leaves, "sh_rest": strided}
    params = copy_of(leaves)  # contiguous copies: the optimizer's moments have the right shapes
    step = step_of(optimizer_with_history(params, torch.Generator().manual_seed(3)), params)
    with pytest.raises(ValueError, match="sh_rest in place"):
        render_loss(scene, leaves, degree, step)
    assert torch.equal(strided, wide[..., ::2])


def test_a_step_needs_the_coefficients_in_two_tensors():
    scene, leaves, _ = split_scene("cpu", 3)
    adam = optimizer_with_history(leaves, torch.Generator().manual_seed(3))
    step = step_of(adam, leaves)
    with pytest.raises(ValueError, match="sh_rest"):
        rasterize(
            leaves["means"],
            leaves["quats"],
            leaves["scales"],
            leaves["opacities"],
            torch.cat([leaves["sh"], leaves["sh_rest"]], 1),
            viewmat=scene.viewmat,
            K=scene.K,
            width=40,
            height=28,
            sh_step=step,
        )
