"""``--sync-free``: renders into slots sized by each view's last count, no read of the count, and
the iterations after an overflow taken again. The reference is the same training with every count
read (the default), compared parameter for parameter: on the CPU they must be equal bit for bit."""

import json

import pytest
import torch
from helpers import DEFAULT_DEVICE, ITERS, SHORT, assert_same_model, train_briefly, train_once

import cdcgs.render
import cdcgs.train.lookahead as lookahead
from cdcgs.errors import OptionError
from cdcgs.render import rasterize
from cdcgs.train.mcmc import position_noise
from cdcgs.train.model import GaussianModel
from cdcgs.train.optim import FusedAdam

CPU_ONLY = pytest.mark.skipif(
    DEFAULT_DEVICE != "cpu", reason="bit-equal runs on the CPU only: on CUDA the order of float atomic adds varies"
)
MCMC_SHORT = {"refine_from": 20, "refine_until": 90, "refine_every": 20, "target_gaussians": 1900}


@CPU_ONLY
@pytest.mark.parametrize(
    "strategy, options, overrides",
    [
        ("3dgs", SHORT, {}),
        ("3dgs", SHORT, {"batch_size": 2}),
        ("mcmc", MCMC_SHORT, {}),
    ],
    ids=["3dgs", "3dgs-batch-2", "mcmc"],
)
def test_a_sync_free_training_is_the_one_that_reads_every_count(tiny_scene, tmp_path, strategy, options, overrides):
    counted, _ = train_once(tiny_scene, tmp_path / "counted", strategy, options, **overrides)
    free, result = train_briefly(tiny_scene, tmp_path / "free", strategy, options, sync_free=True, **overrides)
    assert_same_model(counted, free)
    summary = result["sync_free"]
    views = len(free.scene.train)
    # Every view's count comes from one binning before the training: no render read its count.
    assert summary["views_primed"] == views
    assert summary["renders_counted"] == 0
    assert summary["renders_within_capacity"] == ITERS
    assert summary["rewinds"] == 0
    assert json.load(open(tmp_path / "free" / "metrics.json"))["sync_free"] == summary


def test_overflows_halt_every_update_and_are_taken_again(tiny_scene, tmp_path, monkeypatch):
    """Slots exactly the last count: every view whose count grew overflows, often several before a
    read. Each halts Adam, the statistics, MCMC's noise and the guard's means until the read, which
    goes back to the iteration that overflowed: the run ends as the counted one (on CUDA, whose
    atomic sums differ from run to run, as close as two counted runs)."""
    for strategy, options in (("3dgs", SHORT), ("mcmc", MCMC_SHORT)):
        counted, first = train_once(tiny_scene, tmp_path / f"{strategy}-counted", strategy, options)
        monkeypatch.setattr(lookahead, "MARGIN", 1.0)
        monkeypatch.setattr(lookahead, "FLOOR", 0)
        free, result = train_briefly(tiny_scene, tmp_path / f"{strategy}-free", strategy, options, sync_free=True)
        monkeypatch.undo()
        summary = result["sync_free"]
        assert summary["rewinds"] > 3 and summary["iterations_redone"] > summary["rewinds"], summary
        if DEFAULT_DEVICE != "cpu":
            assert abs(result["test"]["psnr"] - first["test"]["psnr"]) < 0.3, (result["test"], first["test"])
            continue
        assert_same_model(counted, free)
        assert counted.guard.means() == free.guard.means()
        assert counted.history["loss"] == free.history["loss"]


@CPU_ONLY
def test_a_halt_on_a_later_view_of_a_batch_also_stops_the_earlier_views_records(tiny_scene, tmp_path, monkeypatch):
    """Batches of two, the first view of each step reading its count and the second rendered into
    exactly its last count's slots: every halt lands on a step's second view, after the first
    view's render. The step's guard records and densification statistics wait for its last render,
    so the halt stops them too, and the step taken again counts each view once."""
    counted, _ = train_once(tiny_scene, tmp_path / "counted", batch_size=2)
    monkeypatch.setattr(lookahead, "MARGIN", 1.0)
    monkeypatch.setattr(lookahead, "FLOOR", 0)
    real, calls = lookahead.Lookahead.capacity, {"n": 0}

    def second_views_only(self, view, gaussians, scale=1):
        calls["n"] += 1  # a step renders both its views before any read: odd calls are first views
        return None if calls["n"] % 2 else real(self, view, gaussians, scale)

    monkeypatch.setattr(lookahead.Lookahead, "capacity", second_views_only)
    free, result = train_briefly(tiny_scene, tmp_path / "free", sync_free=True, batch_size=2)
    assert result["sync_free"]["rewinds"] > 3, result["sync_free"]
    assert_same_model(counted, free)
    assert counted.guard.means() == free.guard.means() and counted.history["loss"] == free.history["loss"]
    for name, value in counted.strategy_state.items():
        assert (
            torch.equal(value, free.strategy_state[name])
            if torch.is_tensor(value)
            else value == free.strategy_state[name]
        )


def test_the_first_overflow_sets_the_halt_once_with_its_iteration_and_count(tiny_scene):
    """note_render_kernel on hand-made renders: the counts of each view land on the device, the
    first overflow (not a later one) is what the read reports, and a read clears the halt."""
    gaussians = GaussianModel.from_points(torch.rand(200, 3) - 0.5, torch.rand(200, 3), device="cpu")
    viewmat = torch.eye(4)
    viewmat[2, 3] = 2.0
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 18], [0, 0, 1]])

    def render(capacity):
        with torch.no_grad():
            return rasterize(**gaussians.render_args(), viewmat=viewmat, K=K, width=48, height=36, capacity=capacity)[2]

    count = rasterize(**gaussians.render_args(), viewmat=viewmat, K=K, width=48, height=36)[2].num_intersections
    assert count > 10
    state = lookahead.Lookahead("cpu", num_views=3)
    state.counted(0, count, gaussians.num)
    assert state.capacity(0, gaussians.num) == int(count * lookahead.MARGIN + 0.999999) + lookahead.FLOOR
    assert state.capacity(0, 2 * gaussians.num) > 2 * count  # grown Gaussians: more slots
    assert state.capacity(0, gaussians.num, scale=2) is None and state.capacity(1, gaussians.num) is None
    state.note(render(count), step=7, view=0, gaussians=gaussians.num)
    assert state.read() is None and int(state.halt) == 0
    state.note(render(count - 1), step=8, view=1, gaussians=gaussians.num)
    state.note(render(count - 5), step=9, view=2, gaussians=gaussians.num)  # a later overflow: not the first
    halted = state.read()
    assert (halted.step, halted.overflowed, halted.count) == (8, True, count)
    assert int(state.halt) == 0 and state.read() is None
    # Every view's count was recorded, overflowed or not.
    assert state.capacity(1, gaussians.num) == state.capacity(2, gaussians.num) == state.capacity(0, gaussians.num)
    # Slots past what a render takes: the count is read instead.
    state.counted(0, cdcgs.render.MAX_CAPACITY, gaussians.num)
    assert state.capacity(0, gaussians.num) is None


def test_a_halt_stops_adam_the_statistics_and_the_noise():
    """The kernels that change a training's state do nothing while ``halt[0]`` is set, and the same
    as without a halt when it is 0."""
    torch.manual_seed(0)
    halt_on, halt_off = torch.ones(1, dtype=torch.int32), torch.zeros(1, dtype=torch.int32)
    results = {}
    for name, halt in (("none", None), ("off", halt_off), ("on", halt_on)):
        p = torch.nn.Parameter(torch.arange(12, dtype=torch.float32).view(4, 3))
        optimizer = FusedAdam([p], lr=0.1)
        for _ in range(2):
            p.grad = torch.ones_like(p)
            optimizer.step(halt=halt)
        results[name] = (p.detach().clone(), optimizer.state[p]["exp_avg"].clone())
    assert torch.equal(results["none"][0], results["off"][0]) and torch.equal(results["none"][1], results["off"][1])
    assert torch.equal(results["on"][0], torch.arange(12, dtype=torch.float32).view(4, 3))
    assert not results["on"][1].any()

    model = GaussianModel.from_points(torch.rand(30, 3), torch.rand(30, 3), device="cpu")
    before = model.params["means"].detach().clone()
    for halt, moved in ((halt_on, False), (halt_off, True)):
        means = model.params["means"].detach()
        position_noise(model, 1e-2, 5e5, 100.0, 0.005, torch.Generator().manual_seed(3), out=means, halt=halt)
        assert (not torch.equal(means, before)) == moved

    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[30.0, 0, 24], [0, 30.0, 18], [0, 0, 1]])
    model = GaussianModel.from_points(torch.rand(30, 3) - 0.5, torch.rand(30, 3), device="cpu")
    image, _, info = rasterize(**model.render_args(), viewmat=viewmat, K=K, width=48, height=36)
    info.means2d.retain_grad()
    image.sum().backward()
    sums = [torch.zeros(30) for _ in range(3)]
    info.accumulate_statistics(*sums, halt=halt_on)
    assert not any(s.any() for s in sums)
    info.accumulate_statistics(*sums, halt=halt_off)
    assert sums[1].sum() == (info.radii > 0).all(dim=1).sum() > 0
    with pytest.raises(ValueError, match="halt must be an int32 tensor"):
        info.accumulate_statistics(*sums, halt=torch.ones(1))


def test_sync_free_refuses_what_a_halt_cannot_stop(tiny_scene, tmp_path):
    with pytest.raises(OptionError, match="--optimizer torch-adam cannot: use adam or selective"):
        train_briefly(tiny_scene, tmp_path / "a", iters=2, sync_free=True, optimizer="torch-adam")
    with pytest.raises(OptionError, match="--complexity-schedule online"):
        train_briefly(tiny_scene, tmp_path / "b", "cdc", {"complexity_schedule": "online"}, iters=2, sync_free=True)
