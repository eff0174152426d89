"""DashGaussian's resolution schedule (``--resolution-schedule dash``): the spectrum windows against
brute force, the schedule on spectra whose answer is known, and a training that follows it; its
primitive budget (``--budget-schedule dash``) against hand computations and in a training."""

import json
import math
from itertools import pairwise

import pytest
import torch
import torch.nn.functional as F
from helpers import DEFAULT_DEVICE, SHORT, interrupt_at, tiny_config

from cdcgs.errors import OptionError
from cdcgs.train.config import LearningRates
from cdcgs.train.schedules import (
    ResolutionSchedule,
    _summed_area,
    dash_budget,
    dash_momentum,
    dash_schedule,
    position_lr,
    solve_window,
    window_energy,
)
from cdcgs.train.trainer import Trainer


@pytest.mark.parametrize("shape", [(37, 52), (40, 40), (9, 14)])
def test_window_energy_is_the_sum_over_the_central_window(shape):
    spectrum = torch.rand(*shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    table = _summed_area(spectrum)
    h, w = shape
    for fraction in (0.05, 0.3, 0.5, 0.77, 1.0):
        ch, cw = (h + 1) // 2, (w + 1) // 2
        hh, hw = int(h * fraction) // 2, int(w * fraction) // 2
        expected = spectrum[ch - hh : ch + hh, cw - hw : cw + hw].sum().item()
        assert window_energy(table, fraction) == pytest.approx(expected, rel=1e-12, abs=1e-12)


def test_a_flat_spectrum_gives_the_scale_of_the_area():
    """Uniform energy: the window of 1/s holds 1/s^2 of it, so a quarter needs s = 2 and a ninth s = 3."""
    table = _summed_area(torch.ones(600, 600, dtype=torch.float64))
    assert solve_window(table, 600 * 600 / 4) == pytest.approx(2.0, rel=0.01)
    assert solve_window(table, 600 * 600 / 9) == pytest.approx(3.0, rel=0.01)


def test_white_noise_photos_start_at_half_size():
    g = torch.Generator().manual_seed(2)
    photos = [(torch.rand(64, 96, 3, generator=g) * 255).to(torch.uint8) for _ in range(3)]
    schedule = dash_schedule(photos, until=15000)
    # A flat spectrum but for the mean's spike at the centre, which the smallest window holds.
    assert 1.8 < schedule.scales[0] <= 2.05
    assert schedule.scale_at(0) == 2 and schedule.scale_at(15000) == 1


def test_smooth_photos_start_low_and_climb_to_full_size():
    g = torch.Generator().manual_seed(3)
    noise = torch.rand(4, 3, 160, 200, generator=g)
    smooth = F.avg_pool2d(F.avg_pool2d(noise, 9, 1, 4, count_include_pad=False), 9, 1, 4, count_include_pad=False)
    photos = [(image.permute(1, 2, 0) * 255).to(torch.uint8) for image in smooth]
    schedule = dash_schedule(photos, until=15000, levels=32)
    assert len(schedule.scales) == 32 and len(schedule.begins) == 33 and schedule.begins[-1] == 15000
    assert schedule.scales[0] == 8.0 and schedule.scales[-1] == 1.0, "capped at 8, ends at full size"
    assert all(a >= b for a, b in pairwise(schedule.scales)), "the scale never rises"
    assert all(a <= b for a, b in pairwise(schedule.begins)), "levels in order"
    steps = list(range(0, 15001, 100))
    scales = [schedule.scale_at(t) for t in steps]
    assert scales[0] == 8 and scales[-1] == 1 and all(a >= b for a, b in pairwise(scales))
    small = dash_schedule([photo[:64, :96] for photo in photos], until=15000)
    assert small.scales[0] == 4.0, "a 64-pixel photo starts at 16 pixels, not at 8"
    assert 0 < schedule.decay_from() < 15000 and schedule.scale_at(schedule.decay_from()) <= 2
    # as DashGaussian: from the step where the climb towards the first level below 2 begins


def test_scale_between_levels_interpolates_the_pixel_count():
    schedule = ResolutionSchedule(scales=(4.0, 2.0, 1.0), begins=(0, 0, 100, 200), until=200)
    # Halfway from 4 to 2: 1/s^2 = (1/16 + 1/4) / 2, s = 2.53 -> 2; just after 100: 2; at 150 between 2 and 1: 1.26 -> 1.
    assert schedule.scale_at(0) == 4 and schedule.scale_at(50) == int(1 / math.sqrt((1 / 16 + 1 / 4) / 2)) == 2
    assert schedule.scale_at(100) == 2 and schedule.scale_at(150) == 1 and schedule.scale_at(250) == 1
    assert schedule.decay_from() == 100


def test_delayed_decay_of_the_position_rate():
    lrs = LearningRates()
    assert position_lr(0, 1000, lrs, 2.0, decay_from=400) == position_lr(400, 1000, lrs, 2.0, decay_from=400)
    assert position_lr(400, 1000, lrs, 2.0, decay_from=400) == pytest.approx(2.0 * lrs.means_init)
    assert position_lr(1000, 1000, lrs, 2.0, decay_from=400) == pytest.approx(2.0 * lrs.means_final)
    assert position_lr(700, 1000, lrs, 1.0, decay_from=400) == pytest.approx(
        math.sqrt(lrs.means_init * lrs.means_final)
    )


def test_training_renders_at_the_scheduled_sizes(tiny_scene, tmp_path, device):
    # every step through trainer._render: not replayed as a CUDA graph (the default on CUDA)
    config = tiny_config(tiny_scene, tmp_path, device, iters=400, resolution_schedule="dash", cuda_graph=False)
    trainer = Trainer(config, {**SHORT, "densify_until": 250})
    trainer._setup()
    trainer.resolution = ResolutionSchedule(scales=(3.0, 1.0), begins=(0, 0, 200), until=250)
    sizes = []
    render = trainer._render

    def spy(*args, **kwargs):
        image, alpha, info = render(*args, **kwargs)
        sizes.append((trainer.step + 1, image.shape[0], image.shape[1]))  # the iteration being rendered
        return image, alpha, info

    trainer._render = spy
    for _ in range(3):
        trainer.train_step()
    view = trainer.scene.train[0]
    assert [s[1:] for s in sizes] == [(view.height // 3, view.width // 3)] * 3
    trainer.step = 299
    trainer.train_step()
    assert sizes[-1] == (300, view.height, view.width), "full size after the schedule's end"
    _, target = trainer._scaled_view(0, 3)
    expected = F.interpolate(
        view.image.permute(2, 0, 1)[None].float() / 255, size=target.shape[:2], mode="bilinear", antialias=True
    )
    expected = (expected[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8)
    assert torch.equal(target, expected)
    trainer._scaled_view(0, 2)
    assert {scale for _, scale in trainer._scaled} == {2}, "one scale's views are kept at a time"
    *_, info_full = render(0)
    *_, info_small = render(0, None, 3)
    seen = info_full.visible & info_small.visible
    torch.testing.assert_close(
        info_small.means2d[seen],
        info_full.means2d[seen]
        * torch.tensor([target.shape[1] / view.width, target.shape[0] / view.height], device=info_full.means2d.device),
        rtol=1e-4,
        atol=1e-3,
    )


def test_a_whole_run_with_the_schedule_and_the_refusal_with_online_complexity(tiny_scene, tmp_path):
    result = Trainer(tiny_config(tiny_scene, tmp_path / "run", iters=60, resolution_schedule="dash"), SHORT).run()
    plain = Trainer(tiny_config(tiny_scene, tmp_path / "plain", iters=60), SHORT).run()
    # Measured: 14.9 dB with the schedule, 15.5 without (60 iterations, most of them at 1/2 size).
    assert result["iterations"] == 60 and result["test"]["psnr"] > plain["test"]["psnr"] - 1.5
    config = tiny_config(tiny_scene, tmp_path / "cdc", iters=5, strategy="cdc", resolution_schedule="dash")
    with pytest.raises(OptionError, match="--complexity-schedule online"):
        Trainer(config, {**SHORT, "complexity_schedule": "online"}).run()
    assert not (tmp_path / "cdc").exists() or not any((tmp_path / "cdc").iterdir())


def test_the_fast_preset_trains_with_its_options_and_an_option_given_wins(tiny_scene, tmp_path):
    """``fast``: 3DGS's rules under DashGaussian's resolution schedule and budget, with selective
    Adam, set by the preset where the run leaves them at none; config.json records them; an
    option the user gives wins, and a run that asks for the budget without the schedule is refused."""

    def trained(name, **options):
        Trainer(tiny_config(tiny_scene, tmp_path / name, **options), SHORT).run()
        return json.loads((tmp_path / name / "config.json").read_text())

    fast = trained("fast", iters=30, strategy="fast")
    assert (fast["train"]["optimizer"], fast["train"]["resolution_schedule"]) == ("selective", "dash")
    assert fast["strategy"]["budget_schedule"] == "dash" and not fast["strategy"]["cdc_densify"]
    mine = trained("mine", iters=5, strategy="fast", optimizer="adam")
    assert (mine["train"]["optimizer"], mine["train"]["resolution_schedule"]) == ("adam", "dash")
    plain = trained("plain", iters=5)
    assert (plain["train"]["optimizer"], plain["train"]["resolution_schedule"]) == ("adam", "none")
    with pytest.raises(OptionError, match="needs --resolution-schedule dash"):
        trained("refused", iters=5, strategy="fast", resolution_schedule="none")


def test_the_budget_rises_with_the_resolution():
    # From 1000 Gaussians to a bound of 11000, densifying every 100 steps until 15000.
    def budget(step, scale, count):
        return dash_budget(step, scale, count, initial=1000, bound=11000, until=15000, every=100)

    # 4^(2 - 1000/15000) = 14.588: 1000 + int(10000 / 14.588) = 1685, under 1500 x 1.2 = 1800.
    assert budget(1000, 4, 1500) == 1685
    assert budget(1000, 4, 1000) == 1200, "at most 20% more in one step"
    assert budget(1000, 4, 5000) == 5000, "above the budget: no growth, and no removal"
    # 2^(2 - 7500/15000) = 2.828: 1000 + int(10000 / 2.828) = 4535.
    assert budget(7500, 2, 4000) == 4535
    assert budget(7500, 1, 10000) == 11000, "full size: the whole bound"
    # The last densification step (14900 + 100 is not before 15000) takes the bound at any scale.
    # 2^(2 - 14800/15000) = 2.019: 1000 + int(10000 / 2.019) = 5954.
    assert budget(14800, 2, 5000) == 5954
    assert budget(14900, 2, 10000) == 11000


def test_the_momentum_follows_the_selected_counts():
    assert dash_momentum(5000, 300) == 5200  # int(0.98 x 5000 + 300)
    assert dash_momentum(5000, 50) == 5000, "4950 is lower: the estimate never falls"
    assert dash_momentum(10, 2_000_000) == 1_000_009, "a step adds at most 1,000,000"


def test_a_whole_run_under_the_budget_and_its_refusal_without_the_schedule(tiny_scene, tmp_path):
    options = {**SHORT, "budget_schedule": "dash"}
    trainer = Trainer(tiny_config(tiny_scene, tmp_path / "run", iters=100, resolution_schedule="dash"), options)
    result = trainer.run()
    assert result["iterations"] == 100 and math.isfinite(result["test"]["psnr"])
    steps = [entry for entry in trainer.history["strategy"] if "gaussians" in entry]
    assert [entry["step"] for entry in steps] == [40, 60, 80, 100]
    bound_start = 1500 + 5 * 1500  # the initial count plus the momentum's start, 5 x 1500
    count, bound = 1500, bound_start
    for entry in steps:
        scale = trainer.resolution.scale_at(entry["step"] - entry["step"] % 100)
        cap = dash_budget(entry["step"], scale, count, 1500, bound, until=120, every=20)
        assert count + entry["cloned"] + entry["split"] <= cap, entry
        count, bound = entry["gaussians"], entry["budget_bound"]
    assert count == trainer.model.num
    # Measured: the first step selects about 1900 of the 1500 (split or cloned) and the 20% step binds.
    assert steps[0]["gaussians"] == 1800 and steps[0]["budget_bound"] > bound_start
    with open(tmp_path / "run" / "config.json") as f:
        strategy = json.load(f)["strategy"]
    assert strategy["budget_schedule"] == "dash" and strategy["budget_max"] is None
    # A bound at the initial count: no growth at all.
    capped = Trainer(
        tiny_config(tiny_scene, tmp_path / "capped", iters=60, resolution_schedule="dash"),
        {**options, "budget_max": 1500},
    )
    capped.run()
    assert capped.model.num <= 1500
    assert all(entry.get("cloned", 0) + entry.get("split", 0) == 0 for entry in capped.history["strategy"])
    with pytest.raises(OptionError, match="needs --resolution-schedule dash"):
        Trainer(tiny_config(tiny_scene, tmp_path / "plain", iters=5), options).run()
    assert not (tmp_path / "plain").exists() or not any((tmp_path / "plain").iterdir())


@pytest.mark.skipif(DEFAULT_DEVICE != "cpu", reason="bitwise repeatable on the CPU only")
def test_a_run_under_the_budget_resumes_exactly(tiny_scene, tmp_path, monkeypatch):
    """The budget's state (the initial count, the momentum) lives in the checkpoint: a run stopped
    between two densification steps and resumed ends as the run that was never stopped."""
    options = {**SHORT, "budget_schedule": "dash"}

    def config(out, **extra):
        return tiny_config(tiny_scene, tmp_path / out, iters=90, resolution_schedule="dash", **extra)

    straight = Trainer(config("a"), options)
    straight.run()
    with monkeypatch.context() as patch:
        interrupt_at(patch, 50)
        with pytest.raises(KeyboardInterrupt):
            Trainer(config("b"), options).run()
    resumed = Trainer(config("b", resume=True), options)
    resumed.run()
    assert [e.get("budget_bound") for e in resumed.history["strategy"]] == [
        e.get("budget_bound") for e in straight.history["strategy"]
    ]
    for name, p in straight.model.params.items():
        assert torch.equal(resumed.model.params[name], p), name
