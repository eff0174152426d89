"""SelectiveAdam (``--optimizer selective``) against a float64 Adam written out here, torch's Adam,
the densification surgery and a training step."""

import pytest
import torch
from helpers import SHORT, hand_model, tiny_config

from cdcgs.train import ops
from cdcgs.train.config import LearningRates
from cdcgs.train.optim import SelectiveAdam
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
    optimizer = SelectiveAdam([{"params": [p]} for p in live.values()], lr=lr, betas=betas, eps=eps)
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
    ours = SelectiveAdam([a], lr=0.003, eps=1e-15)
    theirs = torch.optim.Adam([b], lr=0.003, eps=1e-15)
    for _ in range(5):
        grad = torch.randn(50, 3, generator=g).to(device)
        a.grad, b.grad = grad.clone(), grad.clone()
        ours.step()
        theirs.step()
    torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(ours.state[a]["exp_avg_sq"], theirs.state[b]["exp_avg_sq"])


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
    optimizer = SelectiveAdam([{"params": [first]}, {"params": [p]}], lr=0.1)
    with pytest.raises(ValueError, match=message):
        optimizer.step(mask)
    assert torch.equal(first.detach(), before[0]) and torch.equal(p.detach(), before[1])
    assert not optimizer.state, "no state was created either"


def test_the_surgery_keeps_its_moments_in_step():
    model, adam = hand_model()
    optimizer = ops.make_optimizer(model, LearningRates(), 1.0, "selective")
    assert isinstance(optimizer, SelectiveAdam)
    optimizer.load_state_dict(adam.state_dict())  # Adam's state, as a resume with the other optimizer loads it
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
    optimizer.step(torch.arange(model.num) % 2 == 0)
    for group in optimizer.param_groups:
        state = optimizer.state[group["params"][0]]
        assert float(state["step"]) == 2.0  # loaded 1, one step
        torch.testing.assert_close(state["exp_avg"][1::2], before[group["name"]][~drop][1::2])


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
