"""3DGS-MCMC: the relocation formulas and the position noise against float64 references, the
relocation and growth on hand-built states, and MCMC (with and without CDC) in training runs."""

import json
import math

import numpy as np
import pytest
import reference
import torch
from helpers import DEFAULT_DEVICE, context, hand_model, interrupt_at, moments, tiny_config

from cdcgs.train.mcmc import MCMC, copy_weights, draw_with_replacement, position_noise, relocation
from cdcgs.train.strategies import make_strategy
from cdcgs.train.trainer import Trainer


def line_integral_of_copies(opacity: float, scale: float, n: int) -> float:
    """∫ 1 - (1 - o e^(-x²/2s²))^n dx by the trapezoid rule in float64: the opacity that n copies
    stacked at one place put on a line through their centre."""
    x = np.linspace(-12 * scale, 12 * scale, 400_001)
    y = 1.0 - (1.0 - opacity * np.exp(-0.5 * (x / scale) ** 2)) ** n
    return float(np.trapezoid(y, x))


def test_copy_weights_are_the_papers_double_sum():
    weights = copy_weights(12)
    for n in range(1, 13):
        for o in (0.02, 0.4, 0.93):
            direct = sum(
                math.comb(i - 1, k) * (-1) ** k * o ** (k + 1) / math.sqrt(k + 1)
                for i in range(1, n + 1)
                for k in range(i)
            )
            powers = torch.tensor([o ** (k + 1) for k in range(12)], dtype=torch.float64)
            assert float(weights[n - 1] @ powers) == pytest.approx(direct, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_relocated_copies_keep_the_opacity_at_the_centre_and_along_a_line(n):
    """3DGS-MCMC's requirement: n copies at one place render as the original did, checked
    against an independent float64 quadrature (not the binomial sum of the implementation)."""
    opacities = torch.tensor([0.01, 0.2, 0.6, 0.9, 0.99])
    scales = torch.tensor([[0.3, 1.0, 2.0]]).expand(5, 3)
    new_opacity, new_scales = relocation(opacities, scales, torch.full((5,), n), copy_weights(51))
    assert new_opacity.dtype == torch.float64
    # At the centre: n layers of opacity o' let (1 - o')^n through, as one of opacity o.
    torch.testing.assert_close(1 - (1 - new_opacity) ** n, opacities.double(), rtol=1e-12, atol=1e-12)
    for i, o in enumerate(opacities.tolist()):
        for axis in range(3):
            s, s_new = scales[i, axis].item(), new_scales[i, axis].item()
            original = o * s * math.sqrt(2 * math.pi)
            assert line_integral_of_copies(new_opacity[i].item(), s_new, n) == pytest.approx(original, rel=1e-9)
    if n == 1:
        torch.testing.assert_close(new_scales, scales.double())


def test_position_noise_matches_a_float64_reference():
    model, _ = hand_model()
    with torch.no_grad():
        model.params["quats"][:] = torch.nn.functional.normalize(
            torch.randn(6, 4, generator=torch.Generator().manual_seed(1)), dim=-1
        )
        model.params["opacity_logits"][:] = torch.logit(torch.tensor([0.001, 0.004, 0.005, 0.006, 0.05, 0.9]))
    generator = torch.Generator().manual_seed(5)
    replay = torch.Generator().manual_seed(5)
    noise = position_noise(model, lr=1.6e-4 * 3.0, noise_lr=5e5, k=100.0, t=0.005, generator=generator)
    z = torch.randn(6, 3, generator=replay).double()
    rotation = reference.quat_to_matrix(model.params["quats"].detach().double())
    scales = model.params["log_scales"].detach().double().exp()
    opacity = torch.sigmoid(model.params["opacity_logits"].detach().double())
    expected = torch.zeros(6, 3, dtype=torch.float64)
    for i in range(6):
        covariance = rotation[i] @ torch.diag(scales[i] ** 2) @ rotation[i].T
        gate = 1 / (1 + math.exp(-100 * ((1 - opacity[i].item()) - (1 - 0.005))))  # the MCMC code's op_sigmoid
        expected[i] = covariance @ z[i] * gate * 5e5 * 1.6e-4 * 3.0
    torch.testing.assert_close(noise.double(), expected, rtol=1e-4, atol=1e-12)
    assert noise[5].abs().max() < 1e-20 < noise[0].abs().max()  # opaque Gaussians stay put
    # Added in place to a tensor (the training adds it to the means), the same draws.
    means = model.params["means"].detach().clone()
    version = means._version
    again = position_noise(model, 1.6e-4 * 3.0, 5e5, 100.0, 0.005, torch.Generator().manual_seed(5), out=means)
    assert again is means and means._version > version  # torch is told of the write, as of an in-place op
    torch.testing.assert_close(means, model.params["means"].detach() + noise, rtol=0, atol=1e-7)
    # Unnormalised quaternions are normalised first, as the projection does.
    with torch.no_grad():
        model.params["quats"].mul_(7.5)
    scaled = position_noise(model, 1.6e-4 * 3.0, 5e5, 100.0, 0.005, torch.Generator().manual_seed(5))
    torch.testing.assert_close(scaled, noise, rtol=1e-5, atol=1e-12)
    bad_outs = (
        torch.zeros(6, 3, dtype=torch.float64),
        torch.zeros(5, 3),
        torch.zeros(3, 6).t(),
        torch.zeros(6, 3, device="meta"),
    )
    for bad in bad_outs:
        with pytest.raises(ValueError, match="out must be a contiguous float32"):
            position_noise(model, 1e-3, 5e5, 100.0, 0.005, torch.Generator().manual_seed(5), out=bad)


def test_draws_with_replacement_invert_the_float64_cumulative_sum():
    """Each draw is the first index whose float64 cumulative weight exceeds u * total (u the
    generator's uniforms, numpy's searchsorted the reference); zero weights (at both ends and
    inside) are never drawn, the frequencies follow the weights, and the same state draws the same."""
    weights = torch.tensor([0.0, 1.0, 3.0, 0.0, 6.0, 0.0], device=DEFAULT_DEVICE)
    generator = torch.Generator(device=DEFAULT_DEVICE).manual_seed(5)
    again = torch.Generator(device=DEFAULT_DEVICE).set_state(generator.get_state())
    drawn = draw_with_replacement(weights, 200_000, generator)
    u = torch.rand(200_000, dtype=torch.float64, device=DEFAULT_DEVICE, generator=again).cpu().numpy()
    cdf = np.cumsum(weights.cpu().double().numpy())
    np.testing.assert_array_equal(drawn.cpu().numpy(), np.searchsorted(cdf, u * cdf[-1], side="right"))
    counts = torch.bincount(drawn.cpu(), minlength=6).double() / 200_000
    assert counts[[0, 3, 5]].sum() == 0
    torch.testing.assert_close(counts[[1, 2, 4]], torch.tensor([0.1, 0.3, 0.6], dtype=torch.float64), atol=5e-3, rtol=0)
    same = draw_with_replacement(weights, 200_000, torch.Generator(device=DEFAULT_DEVICE).manual_seed(5))
    assert torch.equal(same, drawn)
    # trailing zero weights are never drawn either
    assert int(draw_with_replacement(torch.tensor([2.0, 0.0, 0.0]), 1000, torch.Generator()).max()) == 0
    for bad in (torch.zeros(4), torch.tensor([1.0, float("nan")]), torch.zeros(0), torch.tensor([1.0, -5.0, 10.0])):
        with pytest.raises(ValueError, match="non-negative and not all zero"):
            draw_with_replacement(bad, 3, torch.Generator())


def test_regularizer_is_the_mean_opacity_and_scale():
    model, optimizer = hand_model()
    strategy = make_strategy("mcmc", {"opacity_reg": 0.01, "scale_reg": 0.02})
    term = strategy.regularizer(context(model, optimizer, None, step=1))
    expected = 0.01 * model.opacities().mean() + 0.02 * model.scales().mean()
    torch.testing.assert_close(term, expected)
    term.backward()
    o = model.opacities().detach()
    torch.testing.assert_close(model.params["opacity_logits"].grad, 0.01 * o * (1 - o) / 6)
    assert make_strategy("mcmc", {"opacity_reg": 0.0, "scale_reg": 0.0}).regularizer(None) is None


def test_relocation_moves_the_dead_onto_live_gaussians():
    model, optimizer = hand_model()  # Gaussian 5 (opacity 0.001) is dead
    with torch.no_grad():
        model.params["opacity_logits"][2] = math.log(0.004 / 0.996)  # and 2
    before = {name: p.detach().clone() for name, p in model.params.items()}
    strategy = make_strategy("mcmc", {"target_gaussians": 6})
    log = strategy.after_backward(context(model, optimizer, None, step=600, seed=3), strategy.initialize_state(model))
    assert log["relocated"] == 2 and log["added"] == 0 and model.num == 6
    means = model.params["means"].detach()
    live = [0, 1, 3, 4]
    sources = [int(means[t, 0].item()) for t in (2, 5)]  # the targets now sit on their sources
    assert all(s in live for s in sources)
    copies = {s: sources.count(s) + 1 for s in sources}
    for s, n in copies.items():
        o, scale = relocation(
            torch.tensor([0.5]), before["log_scales"][s : s + 1].exp(), torch.tensor([n]), copy_weights(51)
        )
        for index in [s] + [t for t, src in zip((2, 5), sources) if src == s]:
            assert model.opacities()[index].item() == pytest.approx(o.item(), rel=1e-5)
            torch.testing.assert_close(model.scales()[index].detach().double(), scale[0], rtol=1e-5, atol=0)
    for name in model.params:  # the sources' moments restart; the filled slots keep theirs (the MCMC code)
        m = moments(optimizer, name)["exp_avg"].reshape(6, -1)[:, 0]
        assert (m[sorted(copies)] == 0).all()
        torch.testing.assert_close(m[[2, 5]], torch.tensor([3.0, 6.0]))
    untouched = [i for i in live if i not in copies]
    for name, p in model.params.items():
        torch.testing.assert_close(p[untouched].detach(), before[name][untouched])


@pytest.mark.parametrize("reset", [False, True])
def test_the_filled_slots_keep_or_restart_their_moments(reset):
    model, optimizer = hand_model()  # Gaussian 5 (opacity 0.001) is dead
    strategy = make_strategy("mcmc", {"target_gaussians": 6, "reset_target_moments": reset})
    log = strategy.after_backward(context(model, optimizer, None, step=600, seed=3), strategy.initialize_state(model))
    assert log["relocated"] == 1
    for name in model.params:
        slot = moments(optimizer, name)["exp_avg"].reshape(6, -1)[5, 0].item()
        assert slot == (0.0 if reset else 6.0)


def test_consistency_draws_enter_mcmc_as_relocations():
    """mcmc-cdc: the drawn flat-but-crowded Gaussian is relocated (not deleted), onto the drawn
    complex-but-sparse one first."""
    model, optimizer = hand_model()
    with torch.no_grad():
        model.params["opacity_logits"][5] = 0.0  # nobody is dead by opacity
    strategy = make_strategy("mcmc-cdc", {"target_gaussians": 6})
    favoured = torch.tensor([False, False, False, True, False, False])
    crowded = torch.tensor([False, True, False, False, False, False])
    strategy.measure = lambda ctx, state: (torch.zeros(6), torch.ones(6), {})
    strategy.consistency_draws = lambda ctx, gamma, psi: (favoured, crowded, {})
    log = strategy.relocate(context(model, optimizer, None, step=600), {})
    assert log["relocated"] == 1 and model.num == 6
    means = model.params["means"][:, 0].detach()
    assert means[1].item() == 3.0, "the crowded Gaussian now sits on the favoured one"
    o, _ = relocation(torch.tensor([0.5]), torch.ones(1, 3), torch.tensor([2]), copy_weights(51))
    assert model.opacities()[1].item() == pytest.approx(o.item(), rel=1e-5)
    assert model.opacities()[3].item() == pytest.approx(o.item(), rel=1e-5)


@pytest.mark.parametrize("budget, added", [(100, 2), (41, 1), (40, 0)])
def test_growth_adds_five_percent_up_to_the_budget(budget, added):
    model, optimizer = hand_model(40)
    with torch.no_grad():
        model.params["opacity_logits"][:] = 0.0  # all alive, opacity 0.5
    strategy = make_strategy("mcmc", {"target_gaussians": budget})
    log = strategy.grow(context(model, optimizer, None, step=600))
    assert log["added"] == added == min(budget, int(1.05 * 40)) - 40 and model.num == 40 + added
    # The copies sit on their sources, which share their new, lower opacity.
    for i in range(40, model.num):
        source = int(model.params["means"][i, 0].item())
        assert model.opacities()[i].item() == pytest.approx(model.opacities()[source].item())
        assert model.opacities()[i].item() < 0.5


def test_mcmc_grows_to_its_budget_and_stays(tiny_scene, tmp_path):
    options = {"refine_from": 10, "refine_until": 110, "refine_every": 10, "target_gaussians": 1900}
    trainer = Trainer(tiny_config(tiny_scene, tmp_path, strategy="mcmc", iters=120), options)
    result = trainer.run()
    counts = [(e["step"], e["gaussians"]) for e in trainer.history["strategy"]]
    n = 1500
    for step, count in counts:  # min(budget, 1.05 N) at every step, from 1500 points
        n = min(1900, int(1.05 * n))
        assert count == n, (step, count)
    assert result["num_gaussians"] == 1900
    train = json.load(open(tmp_path / "config.json"))["train"]  # 3DGS-MCMC's own settings, recorded
    assert (train["init_opacity"], train["scale_rule"], train["init_scale"], train["lr"]["opacity_logits"]) == (
        0.5,
        "3dgs",
        0.1,
        0.05,
    )


def test_mcmc_cdc_relocates_its_drawn_gaussians_and_keeps_the_budget(tiny_scene, tmp_path):
    options = {"refine_from": 10, "refine_until": 70, "refine_every": 10, "target_gaussians": 1600}
    trainer = Trainer(tiny_config(tiny_scene, tmp_path, strategy="mcmc-cdc", iters=80), options)
    result = trainer.run()
    entries = trainer.history["strategy"]
    assert [e["step"] for e in entries] == [20, 30, 40, 50, 60]
    for e in entries:
        assert -1 <= e["correlation"] <= 1 and e["cdc_prune"] > 0 and e["cdc_densify"] > 0
    assert [e["gaussians"] for e in entries][1:] == [1600] * 4 and result["num_gaussians"] == 1600
    assert result["strategy"]["name"] == "MCMC" and result["strategy"]["cdc_densify"]


@pytest.mark.skipif(DEFAULT_DEVICE != "cpu", reason="bitwise repeatable on the CPU only")
def test_an_mcmc_run_resumes_exactly(tiny_scene, tmp_path, monkeypatch):
    options = {"refine_from": 5, "refine_until": 30, "refine_every": 5, "target_gaussians": 1700}
    straight = Trainer(tiny_config(tiny_scene, tmp_path / "a", strategy="mcmc-cdc", iters=24), options)
    straight.run()
    with monkeypatch.context() as patch:
        interrupt_at(patch, 12)
        with pytest.raises(KeyboardInterrupt):
            Trainer(tiny_config(tiny_scene, tmp_path / "b", strategy="mcmc-cdc", iters=24), options).run()
    resumed = Trainer(tiny_config(tiny_scene, tmp_path / "b", strategy="mcmc-cdc", iters=24, resume=True), options)
    resumed.run()
    for name, p in straight.model.params.items():
        assert torch.equal(resumed.model.params[name], p), name


def test_mcmc_options_are_checked():
    with pytest.raises(ValueError, match="--growth-rate must be in"):
        MCMC(target_gaussians=10, growth_rate=0.0)
    with pytest.raises(ValueError, match="--noise-t must be in"):
        make_strategy("mcmc", {"noise_t": 2.0})
