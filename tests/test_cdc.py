"""CDC-GS: CAAT, z-scores, candidate sets, sampling, presets, and the strategy in a training run."""

import json
import math
import os

import pytest
import torch
from helpers import context, hand_model, tiny_config

from cdcgs.cli import main as cli_main
from cdcgs.train.cdc import CDC, caat_threshold, correlations, draw, pearson, quantile_score, ranks, zscore
from cdcgs.train.presets import PRESETS
from cdcgs.train.trainer import Trainer


def test_caat_threshold_hand_values():
    gamma = torch.tensor([0.0, 1.0, 0.5, -3.0, 7.0])
    tau = caat_threshold(gamma, 1.5e-4, 2e-4, 6.0)
    at_one = 1.5e-4 + 0.5e-4 * (1 - 2 * (1 / (1 + math.exp(-6)) - 0.5))
    at_half = 1.5e-4 + 0.5e-4 * (1 - 2 * (1 / (1 + math.exp(-3)) - 0.5))
    torch.testing.assert_close(tau, torch.tensor([2e-4, at_one, at_half, 2e-4, at_one]))
    assert at_one == pytest.approx(1.5012e-4, rel=1e-3)  # "the most complex gets about 1.5e-4"


def test_zscores_and_candidate_sets():
    gamma = torch.tensor([0.9, 0.8, 0.1, 0.0, 0.5, 0.2])
    psi = torch.tensor([1.0, 9.0, 8.0, 2.0, 5.0, 5.0])
    zg, zp = zscore(gamma), zscore(psi)
    torch.testing.assert_close(zg, (gamma - gamma.mean()) / (gamma.std() + 1e-6))
    s = zg * zp
    complex_sparse = ((s < 0) & (zg > 0)).tolist()
    flat_crowded = ((s < 0) & (zg < 0)).tolist()
    # mean Gamma 0.4167, mean Psi 5: Gaussian 0 is complex and sparse, 2 is flat and crowded;
    # 1 (complex, crowded) and 3 (flat, sparse) agree; 4, 5 sit at the mean density (z = 0).
    assert complex_sparse == [True, False, False, False, False, False]
    assert flat_crowded == [False, False, True, False, False, False]
    q = quantile_score(psi, 0.25)
    torch.testing.assert_close(q, (psi - torch.quantile(psi, 0.25)) / (psi.std() + 1e-6))


def test_pearson():
    a = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert pearson(a, 2 * a + 1) == pytest.approx(1.0)
    assert pearson(a, -a) == pytest.approx(-1.0)
    assert pearson(a, torch.ones(4)) == 0.0


def brute_ranks(x):
    """1-based ranks, ties averaged, by counting (O(N^2))."""
    values = x.tolist()
    return torch.tensor(
        [sum(v < w for v in values) + (sum(v == w for v in values) + 1) / 2 for w in values], dtype=torch.float64
    )


def test_rank_statistics_match_brute_force_with_ties():
    g = torch.Generator().manual_seed(3)
    gamma = (torch.rand(300, generator=g) * 5).floor() / 5  # many ties, as Γ's zeros
    psi = torch.exp(torch.randn(300, generator=g) * 3)
    psi[:40] = 1 / 1.1e-6  # saturated near-duplicates
    torch.testing.assert_close(ranks(gamma), brute_ranks(gamma))
    torch.testing.assert_close(
        ranks(torch.tensor([3.0, 1.0, 3.0, 2.0])), torch.tensor([3.5, 1.0, 3.5, 2.0], dtype=torch.float64)
    )
    stats = correlations(gamma, psi)
    assert stats["correlation"] == pytest.approx(pearson(gamma, psi))
    assert stats["correlation_log_density"] == pytest.approx(pearson(gamma, psi.log()))
    assert stats["correlation_rank"] == pytest.approx(pearson(brute_ranks(gamma), brute_ranks(psi)))
    assert stats["saturated_density"] == pytest.approx((40 + int((psi[40:] >= 5e5).sum())) / 300)
    # Ranks see through the tail: a monotone transform leaves Spearman unchanged, not Pearson.
    assert correlations(gamma, psi**3)["correlation_rank"] == pytest.approx(stats["correlation_rank"])


def test_draw_counts_candidates_no_duplicates():
    g = torch.Generator().manual_seed(0)
    weights = torch.tensor([0.0, 1.0, 0.0, 2.0, 3.0, 0.0, 4.0])
    mask = draw(weights, 3, g)
    assert mask.sum() == 3 and not mask[weights == 0].any()
    assert draw(weights, 10, g).tolist() == (weights > 0).tolist()  # fewer candidates than asked
    assert not draw(weights, 0, g).any() and not draw(torch.zeros(5), 2, g).any()


def test_draw_probabilities_follow_weights():
    g = torch.Generator().manual_seed(1)
    weights = torch.tensor([1.0, 2.0, 3.0, 4.0])
    counts = torch.zeros(4)
    trials = 20000
    for _ in range(trials):
        counts += draw(weights, 1, g).float()
    expected = weights / weights.sum() * trials
    # Chi-square with 3 degrees of freedom: 16.3 is the 0.1% critical value.
    chi2 = (((counts - expected) ** 2) / expected).sum().item()
    assert chi2 < 16.3, f"frequencies {counts.tolist()} vs expected {expected.tolist()}"


def test_presets_cover_the_variants_table():
    assert set(PRESETS) == {
        "3dgs",
        "absgs",
        "cdc",
        "cdc-hq",
        "caat-only",
        "cdc-only",
        "cdc-prune-only",
        "cdc-reverse",
        "cdc-compact",
        "mcmc",
        "mcmc-cdc",
        "fast",  # not a variant of the paper: issue 21's speed features, test_resolution.py
    }
    cdc = CDC.from_preset("cdc")
    assert (
        isinstance(cdc, CDC) and cdc.rho_densify == 0.01 and cdc.rho_prune == 0.01 and cdc.caat and cdc.periodic_prune
    )
    assert CDC.from_preset("cdc-hq").rho_densify == 0.02
    assert not CDC.from_preset("cdc-only").caat
    po = CDC.from_preset("cdc-prune-only")
    assert po.cdc_prune and not po.cdc_densify and not po.caat and po.periodic_prune
    assert CDC.from_preset("cdc-reverse").reverse
    compact = CDC.from_preset("cdc-compact")
    assert compact.centre == "quantile" and compact.rho_prune == 0.5
    baseline = CDC.from_preset("3dgs")
    assert not (
        baseline.cdc_densify
        or baseline.cdc_prune
        or baseline.caat
        or baseline.periodic_prune
        or baseline.needs_complexity
    )
    assert baseline.prune_screen_size == 0.0  # the 3DGS code's screen-size rule never fires
    with pytest.raises(ValueError, match="--complexity-schedule must be one of full, online"):
        CDC.from_preset("cdc", {"complexity_schedule": "sometimes"})


def test_the_cdc_presets_default_to_the_authors_settings():
    from cdcgs.train.config import LearningRates, TrainConfig, config_to_dict, resolve_defaults
    from cdcgs.train.strategies import make_strategy

    cdc, baseline = CDC.from_preset("cdc"), CDC.from_preset("3dgs", {"log_correlation": True})
    assert cdc.w_max == "alpha" and not cdc.racy_max and cdc.periodic_prune_newborns and cdc.cap_rule == "skip"
    # The baseline measures Γ as CDC does: every view at each densification step, the same w_max.
    assert (baseline.complexity_schedule, baseline.w_max) == (cdc.complexity_schedule, cdc.w_max) == ("full", "alpha")
    # One set of learning rates and initial scales for every ADC-family preset, the CDC-GS code's...
    for name in ("3dgs", "cdc", "cdc-prune-only"):
        config = resolve_defaults(TrainConfig(), CDC.from_preset(name))
        assert (config.lr.opacity_logits, config.scale_rule, config.init_scale, config.init_opacity) == (
            0.025,
            "cdc",
            1.0,
            0.1,
        )
    # ... 3DGS-MCMC's own, and what the user sets wins.
    mcmc = make_strategy("mcmc")
    config = resolve_defaults(TrainConfig(), mcmc)
    assert (config.lr.opacity_logits, config.scale_rule, config.init_scale, config.init_opacity) == (
        0.05,
        "3dgs",
        0.1,
        0.5,
    )
    mine = TrainConfig(lr=LearningRates(opacity_logits=0.01), scale_rule="cdc", init_scale=2.0, init_opacity=0.3)
    config = resolve_defaults(mine, mcmc)
    assert (config.lr.opacity_logits, config.scale_rule, config.init_scale, config.init_opacity) == (
        0.01,
        "cdc",
        2.0,
        0.3,
    )
    # A resumed run keeps what it started with, also after the defaults changed (0.05 and the
    # arithmetic mean before 099f11f); an explicit option still wins.
    saved = config_to_dict(TrainConfig(lr=LearningRates(opacity_logits=0.05), scale_rule="3dgs", init_opacity=0.1))
    config = resolve_defaults(TrainConfig(), CDC.from_preset("cdc"), saved)
    assert (config.lr.opacity_logits, config.scale_rule) == (0.05, "3dgs")
    config = resolve_defaults(TrainConfig(lr=LearningRates(opacity_logits=0.02)), CDC.from_preset("cdc"), saved)
    assert config.lr.opacity_logits == 0.02
    with pytest.raises(ValueError, match="needs --pixel-aggregation max"):
        CDC.from_preset("cdc", {"racy_max": True, "pixel_aggregation": "mean"})


@pytest.mark.parametrize("newborns", [True, False])
def test_periodic_prune_judges_the_newborns_as_the_authors_code(newborns):
    model, optimizer = hand_model()
    with torch.no_grad():
        model.params["opacity_logits"][0] = math.log(0.05 / 0.95)  # 0 is below 0.1 and will be cloned
    strategy = CDC(
        cdc_densify=False, cdc_prune=False, caat=False, log_correlation=False, periodic_prune_newborns=newborns
    )
    state = strategy.initialize_state(model)
    state["grad_sum"] = torch.tensor([5e-4, 0, 0, 0, 0, 0])
    state["count"] = torch.ones(6)
    log = strategy.densify_and_prune(context(model, optimizer, None, step=3000), state)
    assert log["cloned"] == 1
    # After growth: 0, its clone and 5 are below 0.1; before it only 0 and 5 were there to judge.
    assert log["periodic_prune"] == (3 if newborns else 2)
    assert model.num == 7 - log["periodic_prune"]


def test_periodic_prune_replaces_per_step_pruning():
    model, optimizer = hand_model()
    strategy = CDC(cdc_densify=False, cdc_prune=False, caat=False, log_correlation=False)
    max_radius = torch.full((6,), 100.0)
    assert not strategy.prune_mask(context(model, optimizer, None, step=9000), max_radius).any()
    state = strategy.initialize_state(model)
    state["count"] = torch.ones(6)
    # Opacities: 0.5 (0-4), 0.001 (5). At a multiple of 3000, opacity < 0.1 goes.
    log = strategy.densify_and_prune(context(model, optimizer, None, step=3000), state)
    assert log["periodic_prune"] == 1 and model.num == 5
    log = strategy.densify_and_prune(context(model, optimizer, None, step=3100), state)
    assert "periodic_prune" not in log and model.num == 5


@pytest.mark.parametrize("schedule", ["full", "online"])
def test_cdc_trains_and_logs(tiny_scene, tmp_path, schedule):
    config = tiny_config(tiny_scene, tmp_path, strategy="cdc", iters=60, save_maps=2)
    options = {
        "densify_from": 10,
        "densify_until": 50,
        "densify_every": 10,
        "complexity_schedule": schedule,
        "periodic_prune_every": 30,
    }
    trainer = Trainer(config, options)
    result = trainer.run()
    steps = [e for e in trainer.history["strategy"] if "correlation" in e]
    assert [e["step"] for e in steps] == [20, 30, 40]  # none at densify_until itself (strict, as INRIA)
    for entry in steps:
        assert -1 <= entry["correlation"] <= 1
        assert entry["cdc_densify"] > 0 and entry["cdc_prune"] > 0
    assert any("periodic_prune" in e for e in trainer.history["strategy"])
    assert sorted(os.listdir(tmp_path / "complexity_maps")) == ["view_001.png", "view_002.png"]
    assert (tmp_path / "correlation.png").stat().st_size > 1000
    assert result["strategy"]["complexity_schedule"] == schedule
    # Draw counts: floor(rho x N) of the Gaussians at each step, or every candidate when fewer.
    for e in steps:
        assert e["cdc_densify"] == min(math.floor(0.01 * e["gaussians_before"]), e["densify_candidates"])
        assert e["cdc_prune"] == min(math.floor(0.01 * e["gaussians_before"]), e["prune_candidates"])
    # Time: each refinement's seconds hold its Γ and Ψ seconds; the run's totals are their sums.
    for e in steps:
        assert e["gamma_seconds"] > 0 and e["psi_seconds"] > 0
        assert e["gamma_seconds"] + e["psi_seconds"] <= e["refine_seconds"]
    events = trainer.history["strategy"]
    for key in ("refine_seconds", "gamma_seconds", "psi_seconds"):
        assert result[key] == pytest.approx(sum(e.get(key, 0.0) for e in events))
    assert 0 < result["gamma_seconds"] + result["psi_seconds"] < result["refine_seconds"] < result["train_seconds"]


def test_compare_plots_runs(tiny_scene, tmp_path, capsys):
    for name, opts in (("cdc", {}), ("3dgs", {"log_correlation": True})):
        Trainer(
            tiny_config(tiny_scene, tmp_path / name, strategy=name, iters=30),
            {"densify_from": 10, "densify_until": 25, "densify_every": 10, **opts},
        ).run()
    assert cli_main(["compare", str(tmp_path / "cdc"), str(tmp_path / "3dgs"), "--out", str(tmp_path / "fig.png")]) == 0
    table = capsys.readouterr().out
    history = json.load(open(tmp_path / "cdc" / "history.json"))
    last = [e for e in history["strategy"] if "correlation" in e][-1]
    assert "| cdc (cdc) | 20–20 |" in table and f"{last['correlation_rank']:.3f}" in table
    assert (tmp_path / "fig.png").stat().st_size > 1000
    assert cli_main(["compare", str(tmp_path / "nope")]) == 2
    assert json.load(open(tmp_path / "cdc" / "config.json"))["strategy"]["name"] == "CDC"


def test_the_gamma_pass_bins_the_gaussians_as_they_are_now(tiny_scene, tmp_path):
    """Trainer._bins computes the scales and opacities once for a pass over the views, and again
    after an in-place update or a new parameter tensor: its lists are always those of the current
    Gaussians."""
    from cdcgs.render import bin_view

    trainer = Trainer(tiny_config(tiny_scene, tmp_path / "run", strategy="cdc", iters=2))
    trainer._setup()
    model = trainer.model

    def fresh():
        with torch.no_grad():
            args = {k: model.render_args()[k] for k in ("means", "quats", "scales", "opacities")}
        return bin_view(**args, camera=trainer.cameras[1])

    def same(a, b):
        return all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("conics", "opacities", "sorted_gauss_ids"))

    assert same(trainer._bins(1).finish(), fresh())
    with torch.no_grad():
        model.params["log_scales"].add_(0.3)  # what an optimizer step does
    assert same(trainer._bins(1).finish(), fresh())
    model.params["opacity_logits"] = torch.nn.Parameter(model.params["opacity_logits"].detach() - 2.0)  # surgery
    assert same(trainer._bins(1).finish(), fresh())
    other = Trainer(tiny_config(tiny_scene, tmp_path / "b", strategy="cdc", iters=2))
    other._setup()
    assert not same(trainer._bins(1).finish(), other._bins(1).finish()), "the changes above reached the lists"
