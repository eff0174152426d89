"""``--cuda-graph``: a step (one view, or a batch) replayed as one CUDA graph, with the view, the iteration
and Adam's rates read from the device. On the CPU the same step runs one operation at a time and
must give the training without it bit for bit; on CUDA the replayed training must stay as close to
the counted one as two counted runs are."""

import gc
import weakref

import pytest
import torch
from helpers import (
    DEFAULT_DEVICE,
    ITERS,
    SHORT,
    assert_same_model,
    interrupt_at,
    tiny_config,
    train_briefly,
    train_once,
    warp_without_ordinals,
)

import cdcgs.complexity
import cdcgs.train.lookahead as lookahead
from cdcgs.errors import OptionError
from cdcgs.render import prepare_camera, rasterize
from cdcgs.train.graph import GraphSteps
from cdcgs.train.trainer import Trainer

CPU_ONLY = pytest.mark.skipif(
    DEFAULT_DEVICE != "cpu", reason="bit-equal runs on the CPU only: on CUDA the order of float atomic adds varies"
)


# CDC's online Γ: its hooks read each view's map on the host, so its steps are not captured
ONLINE = {"complexity_schedule": "online"}
# MCMC's schedule for these runs: relocation and growth every 20 iterations (the scene's 1,500
# points grow by 5% each time, to at most the budget), so that the graphs meet new Gaussians too
MCMC_SHORT = {"refine_from": 20, "refine_until": 100, "refine_every": 20, "target_gaussians": 2000}


@CPU_ONLY
@pytest.mark.parametrize(
    "strategy, overrides",
    [
        ("3dgs", {}),
        ("absgs", {"optimizer": "selective"}),
        ("fast", {}),
        ("cdc", {}),
        ("mcmc", {}),
        ("mcmc-cdc", {}),
        ("3dgs", {"batch_size": 2}),
        ("absgs", {"optimizer": "selective", "batch_size": 3}),
        ("cdc", {"batch_size": 2}),
        ("mcmc", {"batch_size": 2}),
    ],
    ids=[
        "3dgs",
        "absgs-selective",
        "fast",
        "cdc",
        "mcmc",
        "mcmc-cdc",
        "3dgs-batch-2",
        "absgs-selective-batch-3",
        "cdc-batch-2",
        "mcmc-batch-2",
    ],
)
def test_a_graph_training_is_the_one_that_reads_every_count(tiny_scene, tmp_path, strategy, overrides):
    """Replayed steps, of one view or of a batch (its views rendered in turn in one graph, the
    gradients averaged, one Adam step), train the steps that run one operation at a time. MCMC's
    regulariser is in the graph and its noise after it, drawn as without graphs."""
    options = MCMC_SHORT if strategy.startswith("mcmc") else SHORT
    counted, _ = train_once(tiny_scene, tmp_path / "counted", strategy, options, background="white", **overrides)
    graphed, result = train_once(
        tiny_scene, tmp_path / "graph", strategy, options, background="white", cuda_graph=True, **overrides
    )
    assert_same_model(counted, graphed)
    assert counted.guard.means() == graphed.guard.means()
    summary = result["cuda_graph"]
    views = len(graphed.scene.train)
    # Every view's count is known before the first step; refinement steps, the first step (Adam
    # makes its state) and those after a new SH degree or a refinement that outgrew the slots run
    # as before: the rest replay.
    refining = sum(graphed.strategy.refines_at(i) for i in range(1, ITERS + 1))
    batch = overrides.get("batch_size", 1)
    assert result["sync_free"]["views_primed"] == views
    assert (ITERS - refining) // (2 * batch) < summary["replayed_steps"] <= (ITERS - refining) // batch
    assert summary["captures"] >= 2  # a refinement replaces the Gaussians: a new capture
    assert summary["capture_seconds"] == summary["capture_wait_seconds"] == 0.0  # nothing captured on the CPU
    # a replayed step of one view takes the SH coefficients' step in their adjoint (selective too)
    fused = summary["sh_adam_in_adjoint_steps"]
    assert fused == summary["replayed_steps"] if batch == 1 else fused == 0


@CPU_ONLY
def test_a_loss_that_also_reads_the_sh_coefficients_is_not_fused_silently(tiny_scene, tmp_path, monkeypatch):
    """The SH coefficients' Adam step in their adjoint sees only the render's gradient: a strategy
    whose regulariser also reads them would lose its share. The replayed step stops with an error
    that names them and the switch; with the switch off the same training replays."""
    import cdcgs.train.graph as graph
    from cdcgs.train.strategy import ADC

    monkeypatch.setattr(ADC, "regularizer", lambda self, ctx: 1e-3 * ctx.model.params["sh_rest"].square().sum())
    with pytest.raises(RuntimeError, match=r"gives sh_rest a gradient besides the render's.*FUSE_SH_ADAM = False"):
        train_briefly(tiny_scene, tmp_path / "fused", "3dgs", SHORT, background="white", cuda_graph=True)
    monkeypatch.setattr(graph, "FUSE_SH_ADAM", False)
    _, result = train_briefly(tiny_scene, tmp_path / "launch", "3dgs", SHORT, background="white", cuda_graph=True)
    assert result["cuda_graph"]["replayed_steps"] > 0 and result["cuda_graph"]["sh_adam_in_adjoint_steps"] == 0


@CPU_ONLY
def test_overflows_in_replayed_steps_are_taken_again(tiny_scene, tmp_path, monkeypatch):
    """Slots of exactly the largest last count: views overflow inside replayed steps, halt, and the
    steps are taken again after the read; the run ends as the counted one."""
    counted, _ = train_once(tiny_scene, tmp_path / "counted", "3dgs", SHORT, background="white")
    monkeypatch.setattr(lookahead, "MARGIN", 1.0)
    monkeypatch.setattr(lookahead, "FLOOR", 0)
    graphed, result = train_briefly(tiny_scene, tmp_path / "graph", "3dgs", SHORT, background="white", cuda_graph=True)
    monkeypatch.undo()
    assert_same_model(counted, graphed)
    assert result["sync_free"]["rewinds"] > 0, result["sync_free"]


@CPU_ONLY
@pytest.mark.parametrize("tight", [False, True], ids=["slots", "slots-of-the-last-count"])
def test_the_gamma_pass_bins_into_slots_and_counts_again_after_an_overflow(tiny_scene, tmp_path, monkeypatch, tight):
    """cdc's Γ passes in a replayed training bin each view whose count the training knows into
    slots, reading nothing back until the pass's end, a launch's worth of views at a time from one
    body (GammaGroups: a CUDA graph on a GPU; here the same body run for each group, groups of two
    so that the last is filled up). With slots of exactly the last count some views overflow and
    they are binned again, their counts read. Either way the run is the one that reads every
    count."""
    counted, _ = train_once(tiny_scene, tmp_path / "counted", "cdc", SHORT, background="white")
    monkeypatch.setattr(cdcgs.complexity, "GAMMA_VIEWS_PER_LAUNCH", 2)
    if tight:
        monkeypatch.setattr(lookahead, "MARGIN", 1.0)
        monkeypatch.setattr(lookahead, "FLOOR", 0)
    graphed, result = train_briefly(tiny_scene, tmp_path / "graph", "cdc", SHORT, background="white", cuda_graph=True)
    monkeypatch.undo()
    assert_same_model(counted, graphed)
    views = result["sync_free"]
    assert views["gamma_views_within"] > 0, views
    assert (views["gamma_views_counted_again"] > 0) == tight, views
    groups = result["cuda_graph"]
    assert groups["gamma_groups"] >= views["gamma_views_within"] // 2 > 0, groups


@CPU_ONLY
def test_an_interrupted_graph_training_resumes_exactly(tiny_scene, tmp_path, monkeypatch):
    """Stopped by a signal in a replayed stretch and resumed: the run the uninterrupted one is (the
    checkpoint holds Adam's step counts as the replays advanced them; the graph is captured anew)."""
    values = dict(iters=ITERS, log_every=25, background="white", strategy="3dgs", cuda_graph=True)
    straight = Trainer(tiny_config(tiny_scene, tmp_path / "a", **values), SHORT)
    straight.run()
    with monkeypatch.context() as patch:
        interrupt_at(patch, 50)
        with pytest.raises(KeyboardInterrupt):
            Trainer(tiny_config(tiny_scene, tmp_path / "b", **values), SHORT).run()
    resumed = Trainer(tiny_config(tiny_scene, tmp_path / "b", resume=True, **values), SHORT)
    result = resumed.run()
    assert result["cuda_graph"]["replayed_steps"] > 0
    assert_same_model(straight, resumed)


def test_the_kernels_read_the_camera_on_the_device(tiny_scene, device):
    """A PreparedCamera whose ``on_device`` holds another view's camera renders that view, image
    and gradients, as the view's own camera does."""
    import dataclasses

    import warp as wp

    from cdcgs.kernels.projection import Camera

    views = tiny_scene_views(tiny_scene)
    a, b = (prepare_camera(v.viewmat, v.K, v.width, v.height) for v in views[:2])
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:  # Warp needs the ordinal
        device = torch.device("cuda", torch.cuda.current_device())
    on_device = wp.array([b.camera], dtype=Camera, device=wp.device_from_torch(device))
    swapped = dataclasses.replace(a, on_device=on_device)
    torch.manual_seed(0)
    n = 300
    means = (torch.randn(n, 3) * 0.6).to(device).requires_grad_()
    quats = torch.randn(n, 4, device=device).requires_grad_()
    scales = (torch.rand(n, 3, device=device) * 0.1 + 0.02).requires_grad_()
    opacities = (torch.rand(n, device=device) * 0.8 + 0.1).requires_grad_()
    sh = torch.randn(n, 16, 3, device=device).mul_(0.3).requires_grad_()
    results = []
    for camera in (b, swapped):
        image, _, _ = rasterize(means, quats, scales, opacities, sh, camera=camera, sh_degree=3)
        grads = torch.autograd.grad(
            (image * torch.linspace(0, 1, image.numel(), device=device).view_as(image)).sum(),
            [means, quats, scales, opacities, sh],
        )
        results.append((image, grads))
    (image_b, grads_b), (image_s, grads_s) = results
    assert image_b.abs().sum() > 0
    assert torch.equal(image_b, image_s)
    for g_b, g_s in zip(grads_b, grads_s):
        if device.type == "cpu":
            assert torch.equal(g_b, g_s)
        else:  # the blend's adjoint adds with atomics, in an order that varies from run to run
            torch.testing.assert_close(g_b, g_s, rtol=1e-4, atol=1e-6)


def tiny_scene_views(scene_dir):
    from cdcgs.io import load_scene

    return load_scene(str(scene_dir), device="cpu").train


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"background": "random"}, "fixed background"),
        ({"strategy": "cdc"}, "complexity-schedule online"),
        ({"optimizer": "torch-adam"}, "torch-adam"),
    ],
)
def test_cuda_graph_refuses_what_it_cannot_capture(tiny_scene, tmp_path, overrides, message):
    values = {"iters": 10, "background": "white", "cuda_graph": True, **overrides}
    options = ONLINE if overrides.get("strategy") == "cdc" else None
    with pytest.raises(OptionError, match=message):
        Trainer(tiny_config(tiny_scene, tmp_path / "run", **values), options).run()


@pytest.mark.parametrize("device", ["cuda"])
@pytest.mark.parametrize("strategy", ["3dgs", "mcmc", "cdc"])
@pytest.mark.skipif(not torch.cuda.is_available(), reason="captures CUDA graphs: needs a CUDA GPU")
def test_a_replayed_training_on_cuda_is_as_close_to_the_counted_one_as_two_counted_runs(
    tiny_scene, tmp_path, device, strategy
):
    """On CUDA the steps are captured and replayed, by default. The blend's atomic sums make two
    runs differ a little, so the replayed run is compared with the spread of two counted runs
    (``--no-cuda-graph``). MCMC: its regulariser captured, its noise drawn after each replay."""
    values = dict(background="white", device=device)
    options = MCMC_SHORT if strategy.startswith("mcmc") else SHORT
    runs = {}
    for name, extra in (("counted", {"cuda_graph": False}), ("again", {"cuda_graph": False}), ("graph", {})):
        trainer, result = train_briefly(tiny_scene, tmp_path / name, strategy, options, **values, **extra)
        runs[name] = (trainer, result)
    summary = runs["graph"][1]["cuda_graph"]
    assert summary["replayed_steps"] > ITERS // 2 and summary["captures"] >= 2, summary
    if strategy == "cdc":  # its Γ passes' groups of views replayed from one graph a pass
        assert summary["gamma_captures"] > 0 and summary["gamma_groups"] > summary["gamma_captures"], summary
    # the host's time in the captures and, apart, its waits for the work queued before them
    assert summary["capture_seconds"] > 0 and summary["capture_wait_seconds"] >= 0, summary
    psnr = {name: result["test"]["psnr"] for name, (_, result) in runs.items()}
    spread = abs(psnr["counted"] - psnr["again"])
    assert abs(psnr["graph"] - psnr["counted"]) <= max(3 * spread, 0.3), psnr
    count = {name: trainer.model.num for name, (trainer, _) in runs.items()}
    assert abs(count["graph"] - count["counted"]) <= max(
        3 * abs(count["counted"] - count["again"]), 0.02 * count["counted"]
    ), count


def test_a_capture_first_frees_an_earlier_steps_graph_that_a_reference_cycle_holds(
    tiny_scene, tmp_path, monkeypatch, device
):
    """Warp builds a kernel module on its first launch, and the exceptions its code generation
    catches keep the calling step's frames, with its tensors and so its autograd graph, in a
    reference cycle until Python's cycle collector runs. On an H200 with an empty kernel cache the
    first capture then failed (the graph's gradient accumulators belong to the default stream).
    Here the first (eager) step's image is held in such a cycle, with the automatic collector off:
    the capture that follows must have freed it, and say so."""
    held, alive_after_capture = [], []
    learn, capture = Trainer._learn, GraphSteps._capture

    def learn_and_hold(self, image, *args):
        if not held:  # the first step's image, in a cycle as a caught exception's frames hold it
            cycle = [image]
            cycle.append(cycle)
            held.append(weakref.ref(image))
        return learn(self, image, *args)

    def capture_and_look(self, *args):
        capture(self, *args)
        alive_after_capture.append(held[0]() is not None)

    monkeypatch.setattr(Trainer, "_learn", learn_and_hold)
    monkeypatch.setattr(GraphSteps, "_capture", capture_and_look)
    collecting = gc.isenabled()
    gc.disable()
    try:
        _, result = train_briefly(
            tiny_scene, tmp_path / "run", "3dgs", SHORT, iters=6, background="white", cuda_graph=True, device=device
        )
    finally:
        if collecting:
            gc.enable()
    assert alive_after_capture == [False], alive_after_capture
    assert result["cuda_graph"]["freed_earlier_graphs"] == 1, result["cuda_graph"]


def test_the_memory_pool_check_asks_warp_for_an_indexed_device(monkeypatch):
    """`--device auto` (and cuda) gives torch.device("cuda") without an index, which Warp's
    device_from_torch cannot look up (every training on CUDA stopped at set-up once): the
    refusal's memory-pool check passes the current ordinal. Stand-ins for the CUDA and Warp calls,
    so this runs on the CPU."""
    import types

    import warp as wp

    from cdcgs.train.graph import graph_refusal

    asked = warp_without_ordinals(monkeypatch, 2)
    monkeypatch.setattr(wp, "is_mempool_supported", lambda device: device != "cuda:2")
    trainer = types.SimpleNamespace(device=torch.device("cuda"), config=None)
    why, _ = graph_refusal(trainer, default=True)
    assert asked == [torch.device("cuda", 2)] and "memory pool" in why


def test_cuda_graph_refuses_the_viewer(tiny_scene, tmp_path, capsys):
    """The viewer renders on its own thread, which would run into the captures: refused before
    anything is written."""
    from helpers import train_argv

    from cdcgs.cli import main as cli_main

    out = tmp_path / "run"
    assert cli_main([*train_argv(tiny_scene, out, 5), "--cuda-graph", "--view"]) == 2
    assert "--view" in capsys.readouterr().err
    assert not out.exists()


class _Viewer:
    """A callback that renders beside the training, as ``cdcgs train --view``'s does."""

    renders_beside_training = True

    def on_start(self, trainer): ...

    def on_step(self, trainer): ...

    def on_end(self, trainer): ...


def _as_on_cuda(monkeypatch) -> None:
    """The default's refusals without the device's own (the CPU), as a CUDA training meets them."""
    import cdcgs.train.graph as graph
    import cdcgs.train.trainer as trainer_module

    monkeypatch.setattr(trainer_module, "graph_refusal", lambda t, default=False: graph.graph_refusal(t))


def test_the_default_on_the_cpu_trains_without_graphs_and_says_why(tiny_scene, tmp_path):
    result = Trainer(tiny_config(tiny_scene, tmp_path / "run", iters=10)).run()
    assert result["cuda_graph"] == {"off": "--cuda-graph replays steps on CUDA: this training runs on cpu"}
    assert "sync_free" not in result


@pytest.mark.parametrize(
    "values, callbacks, off",
    [
        ({"cuda_graph": False}, (), "--no-cuda-graph"),
        ({"strategy": "cdc"}, (), "complexity-schedule online"),
        ({"optimizer": "torch-adam"}, (), "torch-adam"),
        ({}, (_Viewer(),), "drop --view"),
    ],
    ids=["off", "cdc-online", "torch-adam", "viewer"],
)
def test_the_default_gives_way_where_the_training_cannot_replay(
    tiny_scene, tmp_path, monkeypatch, values, callbacks, off
):
    """Left at none, ``cuda_graph`` replays the steps wherever the training can take it on CUDA,
    else trains without and records why in metrics.json (the explicit option refuses instead)."""
    _as_on_cuda(monkeypatch)
    config = tiny_config(tiny_scene, tmp_path / "run", iters=10, background="white", **values)
    options = ONLINE if values.get("strategy") == "cdc" else None
    result = Trainer(config, options, callbacks=callbacks).run()
    assert off in result["cuda_graph"]["off"], result["cuda_graph"]


def test_a_strategy_without_a_graph_signature_is_not_captured(tiny_scene, tmp_path, monkeypatch):
    """A strategy of the Strategy protocol alone (no ``graph_signature``, e.g. a user's own) says
    nothing of what its hooks read between steps: its steps are not captured, and the refusal says
    so."""
    import cdcgs.train.trainer as trainer_module

    class Plain:  # the wrapped strategy's hooks, without graph_signature
        def __init__(self, inner):
            self._inner = inner

        def __getattr__(self, name):
            if name == "graph_signature":
                raise AttributeError(name)
            return getattr(self._inner, name)

    real = trainer_module.make_strategy
    monkeypatch.setattr(trainer_module, "make_strategy", lambda *args, **kwargs: Plain(real(*args, **kwargs)))
    config = tiny_config(tiny_scene, tmp_path / "run", iters=10, background="white", cuda_graph=True)
    with pytest.raises(OptionError, match=r"cannot replay the 3dgs strategy.s steps.*drop --cuda-graph for it"):
        Trainer(config).run()


def test_cuda_graph_refuses_a_viewer_callback(tiny_scene, tmp_path):
    config = tiny_config(tiny_scene, tmp_path / "run", iters=10, background="white", cuda_graph=True)
    with pytest.raises(OptionError, match="drop --view"):
        Trainer(config, callbacks=[_Viewer()]).run()


@CPU_ONLY
def test_the_default_on_a_gpu_is_the_graph_training(tiny_scene, tmp_path, monkeypatch):
    """With the device's reason taken away (as on CUDA), the default training replays its steps:
    the same run as ``--cuda-graph`` (on the CPU, one operation at a time), bit for bit."""
    given, _ = train_once(tiny_scene, tmp_path / "given", "3dgs", SHORT, background="white", cuda_graph=True)
    _as_on_cuda(monkeypatch)
    default, result = train_briefly(tiny_scene, tmp_path / "default", "3dgs", SHORT, background="white")
    assert result["cuda_graph"]["replayed_steps"] > 0 and default.lookahead is not None
    assert_same_model(given, default)


def test_a_resumed_run_keeps_its_graph_choice():
    """Left at none, ``cuda_graph`` takes the resumed run's value: a run saved before the graphs
    became the default (false) goes on without them, one saved at none decides again, and a value
    given now wins."""
    from cdcgs.train.config import TrainConfig, config_to_dict, resolve_defaults
    from cdcgs.train.strategies import make_strategy

    strategy = make_strategy("3dgs", {})
    for saved, given, expected in ((False, None, False), (None, None, None), (True, None, True), (False, True, True)):
        before = config_to_dict(TrainConfig(cuda_graph=saved))
        assert resolve_defaults(TrainConfig(cuda_graph=given), strategy, before).cuda_graph is expected
    assert resolve_defaults(TrainConfig(), strategy, {}).cuda_graph is None, "a checkpoint without the key"


def test_a_gpu_without_warps_memory_pool_is_refused(monkeypatch):
    """A capture allocates the step's sort and scan buffers from Warp's memory pool: on a GPU
    without one the steps are not replayed (the reason names the pool)."""
    import types

    import warp as wp

    import cdcgs.train.graph as graph

    monkeypatch.setattr(wp, "device_from_torch", lambda device: device)
    monkeypatch.setattr(wp, "is_mempool_supported", lambda device: False)
    trainer = types.SimpleNamespace(device=torch.device("cuda", 0), config=None)
    for default in (False, True):
        why, _ = graph.graph_refusal(trainer, default=default)
        assert "memory pool" in why


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_a_gamma_pass_from_one_graph_is_the_pass_view_by_view(tiny_scene, tmp_path, device, monkeypatch):
    """GammaGroups (a Γ pass's views binned into slots and measured a launch's worth at a time,
    captured once as a CUDA graph and replayed; on the CPU the same body for each group) gives the
    Γ of the pass that bins and measures view by view, bit for bit, with groups of 1, 3 (the last
    one filled up) and 8 views, and with views that overflow their slots (measured again, counted);
    lets go of its graph and buffers after each pass; with a view whose count is unknown, the pass
    goes view by view."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("captures CUDA graphs: needs a CUDA GPU")
    if device == "cpu" and DEFAULT_DEVICE != "cpu":
        pytest.skip("a CPU test, and the CPU is not among the test devices")
    trainer, _ = train_briefly(
        tiny_scene, tmp_path / "run", "cdc", SHORT, background="white", device=device, cuda_graph=True
    )
    groups = trainer.gamma_groups
    assert groups is not None
    maps, n = trainer.complexity_maps, trainer.model.num
    expected = cdcgs.complexity.complexity_over_views(trainer._bins, maps, n, trainer.device)
    assert (expected > 0).sum() > 10
    for size in (1, 3, 8):
        monkeypatch.setattr(cdcgs.complexity, "GAMMA_VIEWS_PER_LAUNCH", size)
        before = groups.groups
        got = cdcgs.complexity.complexity_over_views(trainer._bins, maps, n, trainer.device, groups=groups)
        torch.testing.assert_close(got, expected, atol=0, rtol=0)
        assert groups.groups - before == -(-len(maps) // size)
        assert groups._graph is None and groups._flags is None and groups._infos is None  # let go after the pass
    # a view whose count the training does not know: the pass bins view by view, the same Γ
    known = dict(trainer.lookahead._known)
    del trainer.lookahead._known[next(iter(known))]
    before = groups.groups
    got = cdcgs.complexity.complexity_over_views(trainer._bins, maps, n, trainer.device, groups=groups)
    torch.testing.assert_close(got, expected, atol=0, rtol=0)
    assert groups.groups == before
    trainer.lookahead._known = known
    # every view's last count 1, so that the slots (the largest any view needs) hold 2 pairs: all
    # overflow, add nothing, and are measured again from counted lists
    monkeypatch.setattr(lookahead, "FLOOR", 0)
    for view, (_, _, scale, iteration) in list(trainer.lookahead._known.items()):
        trainer.lookahead._known[view] = (1, n, scale, iteration)
    again = trainer.lookahead.gamma_views["counted_again"]
    got = cdcgs.complexity.complexity_over_views(trainer._bins, maps, n, trainer.device, groups=groups)
    torch.testing.assert_close(got, expected, atol=0, rtol=0)
    assert trainer.lookahead.gamma_views["counted_again"] == again + len(maps)
