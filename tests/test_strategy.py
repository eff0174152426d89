"""Densification on hand-built states: which Gaussians are cloned, split, pruned, reset, and
what happens to their Adam moments."""

import copy
import dataclasses
import math

import pytest
import torch
from helpers import context, fake_info, hand_model, moments

from cdcgs.errors import OptionError
from cdcgs.train import ops
from cdcgs.train.cdc import CDC
from cdcgs.train.config import LearningRates
from cdcgs.train.presets import PRESET_CLASS, PRESETS
from cdcgs.train.schedules import position_lr
from cdcgs.train.strategies import make_strategy, strategy_fields
from cdcgs.train.strategy import ADC


def test_position_learning_rate_schedule():
    lrs = LearningRates()
    assert position_lr(0, 30000, lrs, 2.0) == pytest.approx(1.6e-4 * 2)
    assert position_lr(15000, 30000, lrs, 2.0) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6) * 2)
    assert position_lr(30000, 30000, lrs, 2.0) == pytest.approx(1.6e-6 * 2)
    assert position_lr(40000, 30000, lrs, 2.0) == pytest.approx(1.6e-6 * 2)


def test_gradient_accumulation_over_visible_views():
    model, optimizer = hand_model()
    strategy = ADC()
    state = strategy.initialize_state(model)
    grad = torch.tensor([[1e-6, 0.0], [0.0, 2e-6], [3e-6, 4e-6], [0, 0], [1e-5, 0], [0, 0]])
    visible = torch.tensor([True, True, True, False, True, True])
    for step, radius in ((1, 3.0), (2, 7.0)):
        strategy.accumulate(context(model, optimizer, fake_info(grad, visible, torch.full((6,), radius)), step), state)
    # NDC units: pixel gradient x W/2 (100) in x and x H/2 (50) in y.
    expected = torch.tensor([1e-4, 1e-4, math.hypot(3e-4, 2e-4), 0, 1e-3, 0])
    torch.testing.assert_close(state["grad_sum"], 2 * expected * visible)
    torch.testing.assert_close(state["count"], 2.0 * visible)
    torch.testing.assert_close(state["max_radius"], 7.0 * visible)
    torch.testing.assert_close(strategy.mean_gradient(state), expected * visible)
    # Seen means both radii > 0 (RasterizeInfo.visible): a footprint of zero height is not counted.
    info = fake_info(grad, visible, torch.full((6,), 3.0))
    info.radii[0] = torch.tensor([3, 0], dtype=torch.int32)
    before = {key: state[key].clone() for key in ("grad_sum", "count", "max_radius")}
    strategy.accumulate(context(model, optimizer, info, 3), state)
    assert all(state[key][0] == before[key][0] for key in before) and state["count"][1] == 3.0


def test_clone_split_prune_choose_the_right_gaussians():
    model, optimizer = hand_model()
    strategy = ADC(grad_threshold=2e-4, gaussian_order="appended")
    state = strategy.initialize_state(model)
    # Mean NDC gradients: 0 and 3 above the threshold; 0 is small (clone), 3 large (split).
    state["grad_sum"] = torch.tensor([5e-4, 1e-4, 1e-4, 3e-4, 1e-4, 1e-4])
    state["count"] = torch.ones(6)
    log = strategy.densify_and_prune(context(model, optimizer, None, step=600), state)
    assert log == {"cloned": 1, "split": 1, "pruned": 1, "gaussians": 6 + 1 + 1 - 1}
    x = model.params["means"][:, 0].detach()
    # Order: old without the split parent (0, 1, 2, 4, 5), the clone of 0, the 2 children of 3;
    # then Gaussian 5 (opacity 0.001) is pruned.
    torch.testing.assert_close(x[:5], torch.tensor([0.0, 1.0, 2.0, 4.0, 0.0]))
    children = model.params["means"][5:].detach()
    parent_scale = torch.tensor([0.5, 0.005, 0.005])
    assert (((children - torch.tensor([3.0, 0.0, 0.0])) / parent_scale).abs() < 3).all(), (
        "children inside the parent's 3 sigma"
    )
    torch.testing.assert_close(model.scales()[5:].detach(), (parent_scale / 1.6).expand(2, 3))
    # Adam moments: kept for survivors, zero for the clone and the children, shapes follow.
    for name, p in model.params.items():
        m = moments(optimizer, name)
        assert m["exp_avg"].shape == p.shape and m["exp_avg_sq"].shape == p.shape
        kept = m["exp_avg"].reshape(len(p), -1)[:, 0]
        torch.testing.assert_close(kept, torch.tensor([1.0, 2.0, 3.0, 5.0, 0.0, 0.0, 0.0]))
    # Statistics start again.
    assert state["grad_sum"].shape == (7,) and state["grad_sum"].sum() == 0


def morton_code(cell: tuple[int, int, int]) -> int:
    """Bit b of axis a at bit 3 b + a, one bit at a time."""
    return sum(((cell[axis] >> bit) & 1) << (3 * bit + axis) for bit in range(21) for axis in range(3))


def test_morton_order_sorts_by_the_interleaved_bits_of_the_cells():
    generator = torch.Generator().manual_seed(4)
    means = torch.randn(300, 3, generator=generator) * torch.tensor([10.0, 0.1, 3.0])
    means[100:200] = means[3]  # clones of Gaussian 3: one cell, kept in their order
    low, high = means.min(0).values.double(), means.max(0).values.double()
    top = 2**21 - 1
    cells = [
        tuple(min(top, max(0, int((float(p[a]) - float(low[a])) / float(high[a] - low[a]) * top))) for a in range(3))
        for p in means.float()
    ]
    expected = sorted(range(len(cells)), key=lambda i: (morton_code(cells[i]), i))
    order = ops.morton_order(means).tolist()
    # float32 against float64 cells may put a point on either side of a cell's edge: compare codes
    codes = [morton_code(cells[i]) for i in order]
    assert codes == sorted(codes), "sorted by code"
    assert sorted(order) == list(range(300))
    assert sum(a != b for a, b in zip(order, expected)) <= 4
    at = order.index(3)
    assert order[at : at + 101] == [3, *range(100, 200)], "ties in their order"
    assert ops.morton_order(torch.zeros(0, 3)).shape == (0,)
    odd = means[:5].clone()
    odd[1, 0], odd[2, 2] = float("nan"), float("inf")  # counted as 0, not an error
    assert sorted(ops.morton_order(odd).tolist()) == list(range(5))


def test_a_densification_step_puts_the_gaussians_in_morton_order():
    """The same Gaussians as the appended order, moments and all, in the order of their cells'
    Morton codes; the statistics start again at the new count. On --dist-mode shards (a refinement
    whose context has a whole scene) auto keeps the appended order and morton sorts the process's
    slice alike."""
    runs, start = {}, hand_model()
    with torch.no_grad():  # a scene spread over two axes
        start[0].params["means"][:, 1] = torch.tensor([3.0, 0.0, 2.0, 1.0, 5.0, 4.0])
    runs_of = (
        ("appended", "appended", False),
        ("auto", "auto", False),
        ("shards", "auto", True),
        ("shards, morton", "morton", True),
    )
    for name, order, sharded in runs_of:
        model, optimizer = copy.deepcopy(start)
        strategy = ADC(grad_threshold=2e-4, gaussian_order=order)
        state = strategy.initialize_state(model)
        state["grad_sum"] = torch.tensor([5e-4, 1e-4, 1e-4, 3e-4, 1e-4, 1e-4])
        state["count"] = torch.ones(6)
        ctx = context(model, optimizer, None, step=600)
        if sharded:  # a refinement of this process's slice on --dist-mode shards
            ctx.whole_scene = lambda: pytest.fail("ADC's decisions need no whole scene")
        log = strategy.densify_and_prune(ctx, state)
        runs[name] = model, optimizer, state, log
    for name, p in runs["shards"][0].params.items():
        assert torch.equal(p, runs["appended"][0].params[name]), f"auto on shards sorted the slice: {name}"
        assert torch.equal(runs["shards, morton"][0].params[name], runs["auto"][0].params[name]), name
    (appended, appended_adam, _, log_a), (sorted_, sorted_adam, state, log) = runs["appended"], runs["auto"]
    assert log == log_a
    permutation = ops.morton_order(appended.params["means"].detach())
    assert not torch.equal(permutation, torch.arange(appended.num)), "the test must move some Gaussian"
    for name, p in sorted_.params.items():
        assert torch.equal(p.detach(), appended.params[name].detach()[permutation]), name
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(moments(sorted_adam, name)[key], moments(appended_adam, name)[key][permutation])
        assert sorted_adam.param_groups[[g["name"] for g in sorted_adam.param_groups].index(name)]["params"][0] is p
    assert state["grad_sum"].shape == (sorted_.num,) and state["grad_sum"].sum() == 0


def test_large_gaussians_pruned_only_after_first_reset():
    model, optimizer = hand_model()
    strategy = ADC(reset_every=3000, prune_screen_size=20.0)  # the paper's rule as written
    max_radius = torch.tensor([1.0, 25.0, 1.0, 1.0, 1.0, 1.0])  # 1 is big on screen
    before = strategy.prune_mask(context(model, optimizer, None, step=2000), max_radius)
    after = strategy.prune_mask(context(model, optimizer, None, step=3100), max_radius)
    assert before.tolist() == [False, False, False, False, False, True]
    # After the first reset also 1 (25 px > 20) and 3, 4 (scale 0.5 > 0.1 x extent).
    assert after.tolist() == [False, True, False, True, True, True]
    # The presets leave the screen size alone, as the 3DGS code does (its radii are zeroed before the test).
    for name in ("adc", "3dgs"):  # adc: the name earlier versions wrote for the same rules
        assert CDC.from_preset(name).prune_mask(context(model, optimizer, None, step=3100), max_radius).tolist() == [
            False,
            False,
            False,
            True,
            True,
            True,
        ]


def test_opacity_reset():
    model, optimizer = hand_model()
    ops.reset_opacity(model, optimizer, 0.01)
    opacity = model.opacities().detach()
    torch.testing.assert_close(opacity, torch.tensor([0.01] * 5 + [0.001]))
    m = moments(optimizer, "opacity_logits")
    assert m["exp_avg"].abs().sum() == 0 and m["exp_avg_sq"].abs().sum() == 0
    assert moments(optimizer, "means")["exp_avg"].abs().sum() > 0


def test_reset_runs_on_schedule_and_stops_after_densification():
    model, optimizer = hand_model()
    strategy = ADC(reset_every=3000, densify_until=15000, densify_from=500)
    state = strategy.initialize_state(model)
    info = lambda: fake_info(torch.zeros(model.num, 2), torch.ones(model.num, dtype=torch.bool), torch.ones(model.num))
    assert "opacity_reset" in strategy.after_backward(context(model, optimizer, info(), 3000), state)
    assert "opacity_reset" not in strategy.after_backward(context(model, optimizer, info(), 3001), state)
    assert "opacity_reset" not in strategy.after_backward(context(model, optimizer, info(), 18000), state)


def test_max_gaussians_caps_growth_keeping_the_strongest():
    model, optimizer = hand_model()
    strategy = ADC(max_gaussians=7, cap_rule="fill")
    state = strategy.initialize_state(model)
    state["grad_sum"] = torch.tensor([5e-4, 9e-4, 3e-4, 3e-4, 1e-4, 1e-4])
    state["count"] = torch.ones(6)
    clone, split = strategy.grow_masks(
        context(model, optimizer, None, 600), state, strategy.mean_gradient(state) >= 2e-4
    )
    # Room for one more: the strongest candidate (1) alone.
    assert clone.tolist() == [False, True, False, False, False, False] and not split.any()


def budget_step(strategy, scale=2):
    """A densification step at 600 of 20 hand-made Gaussians rendered at 1/``scale`` size: the
    candidates are 0 and 1 (small: cloned) and 3 and 4 (large: split), strongest 4, 1, 0, 3;
    Gaussian 5 is pruned for its opacity. Returns (log, state)."""
    model, optimizer = hand_model(20)
    state = strategy.initialize_state(model)
    state["grad_sum"] = torch.zeros(20)
    state["grad_sum"][[4, 1, 0, 3]] = torch.tensor([9e-4, 8e-4, 7e-4, 6e-4])
    state["count"] = torch.ones(20)
    ctx = dataclasses.replace(context(model, optimizer, None, 600), resolution_scale=scale)
    return strategy.refine(ctx, state), state


def test_the_dash_budget_caps_growth_keeping_the_strongest():
    free, _ = budget_step(ADC())
    assert (free["cloned"], free["split"], free["pruned"], free["gaussians"]) == (2, 2, 1, 23)
    # Bound 30 from 20 Gaussians at step 600 of 15000, scale 2: 20 + int(10 / 2^1.96) = 20 + int(2.57) = 22,
    # under the 20% step (24): room for two, the strongest, 4 (split) and 1 (cloned).
    log, state = budget_step(ADC(budget_schedule="dash", budget_max=30))
    assert (log["cloned"], log["split"], log["pruned"], log["gaussians"]) == (1, 1, 1, 21)
    assert log["budget_bound"] == 30 and state["budget_initial"] == 20 and state["budget_momentum"] == -1
    # At full size the whole bound, but the 20% step (int(20 x 1.2) = 24) leaves room for all four.
    assert budget_step(ADC(budget_schedule="dash", budget_max=30), scale=1)[0]["gaussians"] == 23
    # No preset bound: 20 + 5 x 20 = 120, 20 + int(100 / 2^1.96) = 45 > 24: all four grow; the
    # momentum takes in the four selected, int(0.98 x 100 + 4) = 102, and the initial count stays.
    log, state = budget_step(ADC(budget_schedule="dash"))
    assert log["gaussians"] == 23 and log["budget_bound"] == 122
    assert state["budget_momentum"] == 102 and state["budget_initial"] == 20
    assert state["grad_sum"].shape == (23,) and not state["grad_sum"].any(), "the statistics do reset"
    # Under a lower --max-gaussians the tighter cap holds.
    log, _ = budget_step(ADC(budget_schedule="dash", budget_max=30, max_gaussians=21, cap_rule="fill"))
    assert (log["cloned"], log["split"]) == (0, 1)
    cdc, _ = budget_step(CDC.from_preset("3dgs", {"budget_schedule": "dash", "budget_max": 30}))
    assert (cdc["cloned"], cdc["split"], cdc["gaussians"]) == (1, 1, 21)


def test_the_dash_budget_refusals():
    with pytest.raises(OptionError, match="--budget-max is the bound of --budget-schedule dash"):
        ADC(budget_max=100)
    with pytest.raises(OptionError, match="--budget-schedule dash cannot be combined with --target-gaussians"):
        ADC(budget_schedule="dash", target_gaussians=100)
    with pytest.raises(OptionError, match="--budget-schedule"):
        ADC(budget_schedule="fast")
    with pytest.raises(OptionError, match="needs --resolution-schedule dash"):
        budget_step(ADC(budget_schedule="dash"), scale=None)


def test_absgrad_mode_uses_absolute_accumulator():
    model, optimizer = hand_model()
    strategy = CDC.from_preset("absgs")
    assert strategy.absgrad and strategy.grad_threshold == 8e-4
    state = strategy.initialize_state(model)
    grad = torch.tensor([[1e-6, -1e-6]] * 6)
    strategy.accumulate(
        context(model, optimizer, fake_info(grad, torch.ones(6, dtype=torch.bool), torch.ones(6)), 1), state
    )
    torch.testing.assert_close(state["grad_sum"], torch.full((6,), math.hypot(2e-4, 1e-4)))


def test_unknown_strategy_and_option():
    with pytest.raises(ValueError, match="unknown strategy 'nope'"):
        CDC.from_preset("nope")
    with pytest.raises(ValueError, match="has no option"):
        CDC.from_preset("3dgs", {"grad_treshold": 1e-4})


def test_every_preset_is_a_strategy():
    from cdcgs.train.presets import PRESETS
    from cdcgs.train.strategy import Strategy

    for name in PRESETS:
        strategy = make_strategy(name)
        assert isinstance(strategy, Strategy), name
        assert strategy.config()["name"] == ("MCMC" if name.startswith("mcmc") else "CDC")
    with pytest.raises(ValueError, match="not a CDC preset"):
        CDC.from_preset("mcmc")
    with pytest.raises(ValueError, match="needs a budget"):
        make_strategy("mcmc", {"target_gaussians": None})
    with pytest.raises(ValueError, match="has no option"):
        make_strategy("mcmc", {"grad_threshold": 1e-4})
    assert isinstance(ADC(), Strategy) and ADC().complexity_maps_method is None
    assert CDC.from_preset("3dgs").complexity_maps_method is None
    assert CDC.from_preset("3dgs", {"log_correlation": True}).complexity_maps_method == "dwt"
    assert CDC.from_preset("cdc", {"complexity_method": "sobel"}).complexity_maps_method == "sobel"


def test_every_strategy_option_has_help():
    for f, _, presets in strategy_fields():
        assert len(f.metadata.get("help", "")) > 10 and presets, f.name


def test_clone_copies_parameters_with_fresh_moments():
    model, optimizer = hand_model()
    before = {name: p.detach().clone() for name, p in model.params.items()}
    ops.clone(model, optimizer, torch.tensor([False, True, False, False, True, False]))
    assert model.num == 8
    for name, p in model.params.items():
        torch.testing.assert_close(p[:6].detach(), before[name])
        torch.testing.assert_close(p[6:].detach(), before[name][[1, 4]])
        m = moments(optimizer, name)
        assert m["exp_avg"][6:].abs().sum() == 0 and m["exp_avg_sq"][6:].abs().sum() == 0
        assert optimizer.param_groups[[g["name"] for g in optimizer.param_groups].index(name)]["params"][0] is p


def test_split_samples_children_from_the_rotated_parent():
    model, optimizer = hand_model()
    # Parent 3 rotated by 90 degrees about z: its long axis (x, 0.5) now lies along y.
    with torch.no_grad():
        model.params["quats"][3] = torch.tensor([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    mask = torch.zeros(6, dtype=torch.bool)
    mask[3] = True
    ops.split(model, optimizer, mask, count=400, generator=torch.Generator().manual_seed(0))
    children = model.params["means"][5:].detach() - torch.tensor([3.0, 0.0, 0.0])
    spread = children.std(dim=0)
    # Standard deviations of the samples: 0.005 along x and z, 0.5 along y (within sampling error).
    torch.testing.assert_close(spread, torch.tensor([0.005, 0.5, 0.005]), rtol=0.1, atol=0.0)


def test_relocate_moves_parameters_and_restarts_their_moments():
    model, optimizer = hand_model()
    before = {name: p.detach().clone() for name, p in model.params.items()}
    new_opacity = torch.tensor([-1.0, -2.0])
    ops.relocate(
        model,
        optimizer,
        targets=torch.tensor([5, 2]),
        sources=torch.tensor([0, 1]),
        new_values={"opacity_logits": new_opacity},
    )
    assert model.num == 6
    torch.testing.assert_close(model.params["means"][[5, 2]].detach(), before["means"][[0, 1]])
    torch.testing.assert_close(model.params["means"][[3, 4]].detach(), before["means"][[3, 4]])
    torch.testing.assert_close(
        model.params["opacity_logits"][[0, 1, 5, 2]].detach(), torch.tensor([-1.0, -2.0, -1.0, -2.0])
    )
    for name in model.params:
        m = moments(optimizer, name)["exp_avg"].reshape(6, -1)[:, 0]
        torch.testing.assert_close(m, torch.tensor([0.0, 0.0, 0.0, 4.0, 5.0, 0.0]))
    with pytest.raises(ValueError, match="no parameters"):
        ops.relocate(model, optimizer, torch.tensor([0]), torch.tensor([1]), {"colour": torch.zeros(1)})


@pytest.mark.parametrize("name", sorted(set(PRESETS) - set(PRESET_CLASS)))
def test_every_preset_fires_its_events_at_the_steps_of_the_inria_code(name):
    """Iterations from 1, strict `iteration < densify_until_iter` (INRIA's train.py, the CDC-GS code)."""
    strategy = CDC.from_preset(name)
    steps = range(1, 30_001)
    assert [t for t in steps if strategy.densifies_at(t)] == list(range(600, 15_000, 100))
    assert [t for t in steps if strategy.resets_at(t)] == [3000, 6000, 9000, 12000]
    assert [t for t in steps if strategy.accumulates_at(t)] == list(range(1, 15_000))
    prunes = [t for t in steps if strategy.periodic_prunes_at(t)]
    assert prunes == ([3000, 6000, 9000, 12000] if strategy.periodic_prune else [])
    assert [t for t in steps if strategy.refines_at(t)] == list(range(600, 15_000, 100))


def test_the_hooks_follow_the_schedule_at_its_edges():
    model, optimizer = hand_model()
    strategy = ADC()
    fired = []
    strategy.densify_and_prune = lambda ctx, state: fired.append(ctx.step) or {}
    state = strategy.initialize_state(model)
    info = lambda: fake_info(torch.zeros(model.num, 2), torch.ones(model.num, dtype=torch.bool), torch.ones(model.num))
    resets = []
    for step in (500, 600, 3000, 12000, 14900, 14999, 15000, 15100, 18000):
        if "opacity_reset" in strategy.after_backward(context(model, optimizer, info(), step), state):
            resets.append(step)
    assert fired == [600, 3000, 12000, 14900] and resets == [3000, 12000]
    counted = state["count"].clone()
    strategy.after_backward(context(model, optimizer, info(), 15000), state)
    assert torch.equal(state["count"], counted), "no statistics at iteration 15000"


@pytest.mark.parametrize("name", sorted(PRESET_CLASS))
def test_mcmc_presets_refine_at_the_steps_of_the_mcmc_code(name):
    """3DGS-MCMC's train.py: `densify_from_iter < iteration < densify_until_iter` (500, 25000), every 100."""
    strategy = make_strategy(name)
    steps = range(1, 30_001)
    assert [t for t in steps if strategy.refines_at(t)] == list(range(600, 25_000, 100))
    assert [t for t in steps if strategy.accumulates_at(t)] == list(range(1, 25_000))


def _ranked_state(model, scores):
    state = ADC().initialize_state(model)
    state["grad_sum"] = torch.tensor(scores)
    state["count"] = torch.ones(model.num)
    return state


def test_the_cap_skips_growth_once_reached_as_the_cdc_gs_code_or_fills():
    model, optimizer = hand_model()
    scores = [5e-4, 1e-4, 1e-4, 3e-4, 1e-4, 1e-4]  # 0 clones, 3 splits: growth 2
    # skip: below the cap the whole growth happens, even past it (6 + 2 > 7)...
    strategy = ADC(max_gaussians=7)
    log = strategy.densify_and_prune(context(model, optimizer, None, step=600), _ranked_state(model, scores))
    assert (log["cloned"], log["split"]) == (1, 1)
    # ... and none once the count has reached it (7 >= 7), while pruning goes on.
    model, optimizer = hand_model()
    strategy = ADC(max_gaussians=6)
    log = strategy.densify_and_prune(context(model, optimizer, None, step=600), _ranked_state(model, scores))
    assert (log["cloned"], log["split"], log["pruned"]) == (0, 0, 1)
    # fill: the strongest candidate that fits.
    model, optimizer = hand_model()
    strategy = ADC(max_gaussians=7, cap_rule="fill")
    log = strategy.densify_and_prune(context(model, optimizer, None, step=600), _ranked_state(model, scores))
    assert (log["cloned"], log["split"]) == (1, 0)


def test_a_target_count_is_refused_where_it_cannot_act():
    strategy = make_strategy("cdc", {"target_gaussians": 1000})
    strategy.check(30_000)
    with pytest.raises(ValueError, match="last densification step, 14900, is after the run's 7000 iterations"):
        strategy.check(7000)
    with pytest.raises(ValueError, match="no iteration densifies"):
        make_strategy("3dgs", {"target_gaussians": 10, "densify_until": 400}).check(30_000)
    with pytest.raises(ValueError, match="above --max-gaussians"):
        make_strategy("3dgs", {"target_gaussians": 10, "max_gaussians": 5})
    make_strategy("3dgs", {"densify_until": 400}).check(30_000)  # no target: nothing to refuse


def test_a_target_more_than_twice_away_is_logged_short():
    model, optimizer = hand_model()
    strategy = ADC(target_gaussians=30, reset_every=30_000)
    log = strategy.densify_and_prune(context(model, optimizer, None, step=14_900), _ranked_state(model, [0.0] * 6))
    # 6 - 1 pruned = 5, cloned to 10: still 20 short.
    assert (log["target_cloned"], log["target_short"], model.num) == (5, 20, 10)


@pytest.mark.parametrize("target", [4, 5, 8, 9])
def test_target_count_is_landed_on_at_the_last_densification_step(target):
    model, optimizer = hand_model()
    # no world-size pruning at 14900; the Gaussians left in the order the steps append them
    strategy = ADC(target_gaussians=target, reset_every=30_000, gaussian_order="appended")
    assert strategy.last_densification() == 14_900
    scores = [5e-4, 1e-4, 1.5e-4, 3e-4, 1e-4, 1e-4]
    # An earlier step only caps growth at the target (strongest first).
    log = strategy.densify_and_prune(context(model, optimizer, None, step=600), _ranked_state(model, scores))
    assert model.num <= max(target, 6 - 1)
    model, optimizer = hand_model()
    opacity_before = model.opacities().detach().clone()
    log = strategy.densify_and_prune(context(model, optimizer, None, step=14_900), _ranked_state(model, scores))
    assert model.num == target, log
    if target == 4:  # growth capped to nothing, 5 left after the rule's prune: the least opaque goes
        assert log["target_pruned"] == 1
        kept = sorted(opacity_before[opacity_before >= 0.005].tolist())[1:]
        torch.testing.assert_close(sorted(model.opacities().detach().tolist()), kept)
    if target == 9:  # 6 + 2 grown - 1 pruned = 7: the two strongest not grown (2, then 1 before 4 by index) cloned
        assert log["target_cloned"] == 2
        x = model.params["means"][:, 0].detach()
        assert sorted(x[-2:].tolist()) == [1.0, 2.0]
