"""Training on sharded Gaussians (``--dist-mode shards``, cdcgs.train.shard_training) on the CPU
with gloo: two processes, each holding a slice of the scene, against one process training the same
batches with every Gaussian."""

import json
import os

import pytest
import torch
from dist_tasks import SCHEDULE, ok, run_here, run_ranks, task_config

from cdcgs.datasets.procedural import make_procedural_scene
from cdcgs.errors import OptionError
from cdcgs.io import load_checkpoint, read_ply
from cdcgs.train.ops import morton_order
from cdcgs.train.shard_training import ShardedTrainer, even_rows, shard_refusal
from cdcgs.train.strategies import make_strategy
from cdcgs.train.trainer import Trainer

pytestmark = pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="this torch has no torch.distributed with gloo",
)

# SCHEDULE (densification at 4 and 8, an opacity reset at 8), with every selected Gaussian cloned:
# no split draws random numbers, so the slices together must take one process's run. The threshold
# selects some Gaussians of each slice, not all, so the slices grow apart. The one-process runs keep
# the order the slices keep (the grown after the others; --gaussian-order auto sorts one process's).
CLONES = {**SCHEDULE, "clone_max_scale": 1e9, "grad_threshold": 2e-3, "gaussian_order": "appended"}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """9 views of 32 x 32 pixels (6 for training, 3 held out) and 48 points."""
    return make_procedural_scene(tmp_path_factory.mktemp("shard_scene"), views=9, width=32, height=32, points=48)


def rows_of(params: dict, names) -> torch.Tensor:
    """[N, sum of widths]: each Gaussian's parameters ``names`` in one row."""
    return torch.cat([params[name].reshape(params[name].shape[0], -1) for name in names], dim=1).double()


# Adam turns a gradient near zero into a step of about its learning rate either way: the rotations
# of these round, isotropic Gaussians get gradients about 0 whose sign the slices' sums (exact to
# 1e-9) can flip, so a few of their entries end up to two steps (2 x 1e-3) apart. Every other
# parameter stays within float32 rounding.
TOLERANCE = {"means": 1e-5, "log_scales": 1e-5, "opacity_logits": 1e-5, "sh_dc": 1e-5, "sh_rest": 1e-5, "quats": 2.5e-3}


def assert_same_gaussians(a: dict, b: dict) -> torch.Tensor:
    """The same Gaussians in any order: the rows of ``a`` and ``b`` paired one to one at the least
    total distance (every parameter but the rotation), each parameter within its TOLERANCE.
    Returns the rows of ``b`` in ``a``'s order."""
    from scipy.optimize import linear_sum_assignment

    matched = [name for name in sorted(a) if name != "quats"]
    x, y = rows_of(a, matched), rows_of(b, matched)
    assert x.shape == y.shape
    # one to one (a clone and its parent can be nearer to each other than to their own match)
    _, order = linear_sum_assignment(torch.cdist(x, y).numpy())
    nearest = torch.as_tensor(order)
    for name, tolerance in TOLERANCE.items():
        difference = (rows_of(a, [name]) - rows_of(b, [name])[nearest]).abs()
        assert difference.max() <= tolerance, f"{name}: {float(difference.max()):.2e}"
        assert (difference > 1e-5).float().mean() < 0.02, f"{name}: too many entries apart"
    return nearest


@pytest.fixture(scope="module")
def runs(scene, tmp_path_factory):
    """A 12-iteration run of three views a step on two processes of a slice each (the second renders
    the last view again in every second round, adding nothing), and on one process."""
    tmp = tmp_path_factory.mktemp("shard_runs")
    common = dict(scene=scene, options=CLONES, checkpoint_every=0, batch_size=3)
    two = ok(run_ranks("train", 2, tmp, timeout=120.0, out=tmp / "two", dist_mode="shards", **common))
    one = ok([run_here("train", out=tmp / "one", **common)])[0]
    return two, one, tmp


def test_two_slices_train_as_one_process_with_every_gaussian(runs):
    (r0, r1), one, tmp = runs
    kinds = {key for event in one["events"] for key in event}
    assert {"cloned", "pruned", "opacity_reset"} <= kinds, "the run must densify, prune and reset"
    assert sum(event.get("cloned", 0) for event in one["events"]) > 0
    assert len(r0["events"]) == len(one["events"])
    for sharded, whole in zip(r0["events"], one["events"]):
        for key in ("step", "cloned", "split", "pruned", "opacity_reset", "gaussians"):
            assert sharded.get(key) == whole.get(key), (key, sharded, whole)
    assert r0["metrics"] == {**one["metrics"], "processes": 2}
    # the slices hold the scene between them, and the checkpoint holds all of it
    assert r0["params"]["means"].shape[0] + r1["params"]["means"].shape[0] == one["metrics"]["num_gaussians"]
    sharded = load_checkpoint(str(tmp / "two" / "checkpoint.pt"), map_location="cpu")
    whole = load_checkpoint(str(tmp / "one" / "checkpoint.pt"), map_location="cpu")
    nearest = assert_same_gaussians(sharded["model"]["params"], whole["model"]["params"])
    # Adam's moments: of the batch's mean gradient (each slice's sum of three views' gradients, the
    # division by the batch folded into Adam's rates) as one process's (which divides the
    # gradients), row for row. The two round differently, and Adam and the colours' clamp at 0 carry
    # that far in a few entries (the SH coefficients' moments up to 2% of the largest apart, 0.5% on
    # average): the mean difference is bounded; a wrong scale (1/3 for 1/9, or none) is 2x to 8x.
    for index, group in enumerate(sharded["optimizer"]["param_groups"]):
        twin = [g["name"] for g in whole["optimizer"]["param_groups"]].index(group["name"])
        for key in ("exp_avg", "exp_avg_sq"):
            mine, theirs = sharded["optimizer"]["state"][index][key], whole["optimizer"]["state"][twin][key][nearest]
            assert (mine - theirs).abs().mean() <= 2e-2 * theirs.abs().mean(), (group["name"], key)
    ply = read_ply(str(tmp / "two" / "point_cloud.ply"))
    torch.testing.assert_close(ply.means, sharded["model"]["params"]["means"])
    # Adam's moments gathered with the parameters: their rows in the parameters' order
    moments = {
        group["name"]: sharded["optimizer"]["state"][index]["exp_avg_sq"]
        for index, group in enumerate(sharded["optimizer"]["param_groups"])
    }
    assert moments["means"].shape == sharded["model"]["params"]["means"].shape
    assert r0["test"]["views"] == 3
    # the test views rendered in rounds through the sharded render (rank 1 renders the third view
    # again in the second round, and drops it)
    assert r0["test"]["psnr"] == pytest.approx(one["test"]["psnr"], abs=1e-3)
    assert r0["test"]["ssim"] == pytest.approx(one["test"]["ssim"], abs=1e-5)
    assert r0["test"]["num_gaussians"] == one["test"]["num_gaussians"]
    assert {"save_checkpoint", "write_ply", "write_json"} <= set(r0["writes"])
    assert r1["writes"] == [], "only rank 0 writes"
    with open(tmp / "two" / "metrics.json") as f:
        metrics = json.load(f)
    assert metrics["dist_mode"] == "shards" and sum(metrics["rows"]) == metrics["num_gaussians"]


def test_a_sharded_checkpoint_resumes_on_its_slices_and_in_one_process(scene, runs, tmp_path):
    """The run's checkpoint, whose slices grew apart in its densifications, resumed for four more
    iterations on two processes (on the slices it records) and in one process: the same run."""
    _, _, tmp = runs
    import shutil

    saved = load_checkpoint(str(tmp / "two" / "checkpoint.pt"), map_location="cpu")["rows"]
    assert saved[0] != saved[1], "the slices should have grown apart"
    for name in ("two", "one"):
        shutil.copytree(tmp / "two", tmp_path / name)
    resumed = dict(scene=scene, options=CLONES, checkpoint_every=0, batch_size=2, iters=16, resume=True)
    ok(run_ranks("train", 2, tmp_path, timeout=120.0, out=tmp_path / "two", dist_mode="shards", **resumed))
    ok([run_here("train", out=tmp_path / "one", **resumed)])
    with open(tmp_path / "two" / "config.json") as f:
        assert json.load(f)["rows"] == saved, "the resumed slices are the checkpoint's"
    sharded, whole = (load_checkpoint(str(tmp_path / n / "checkpoint.pt"), map_location="cpu") for n in ("two", "one"))
    assert sharded["step"] == whole["step"] == 16 and "rows" not in whole
    assert_same_gaussians(sharded["model"]["params"], whole["model"]["params"])


@pytest.mark.parametrize("strategy", ["cdc-only", "cdc"])
def test_cdc_on_two_slices_takes_one_processes_decisions(scene, tmp_path, strategy):
    """CDC-GS on two slices: Γ measured over the gathered scene with the views split over the
    processes, Ψ over the gathered means, the draws from the step's shared stream; ``cdc-only``
    (its draws without CAAT) and ``cdc`` (with CAAT's thresholds, raised so that they leave some
    Gaussians to draw); ``cdc`` with the sharded steps replayed (on the CPU the same body, one
    operation at a time) and its Γ pass measured in groups of views from the gathered scene
    (GammaGroups). To its first densification (at 4) the same candidates, draws, correlations and
    Gaussians as one process with every Gaussian; there each slice is sorted in Morton order, as one
    process sorts the whole scene (--gaussian-order morton: checked where the densification ends the
    run; the replayed run takes two steps more, its first being eager)."""
    options = {**CLONES, "rho_densify": 0.2, "rho_prune": 0.1, "gaussian_order": "morton"}
    replayed = {}
    if strategy == "cdc":
        options.update(tau_low=1.5e-3, tau_up=2.5e-3)
        replayed = {"cuda_graph": True}
    iters = 6 if replayed else 4
    common = dict(scene=scene, strategy=strategy, options=options, checkpoint_every=0, batch_size=2, iters=iters)
    two = run_ranks("train", 2, tmp_path, timeout=120.0, out=tmp_path / "two", dist_mode="shards", **common, **replayed)
    r0, r1 = ok(two)
    for mine in (r0, r1) if replayed else ():  # each process measured its views in groups
        assert mine["cuda_graph"]["gamma_groups"] > 0 and mine["cuda_graph"]["replayed_steps"] > 0, mine["cuda_graph"]
    one = ok([run_here("train", out=tmp_path / "one", **common)])[0]
    assert len(r0["events"]) == len(one["events"]) == 1
    for sharded, whole in zip(r0["events"], one["events"]):
        for key in ("step", "densify_candidates", "prune_candidates", "cdc_densify", "cdc_prune", "cloned", "pruned"):
            assert sharded.get(key) == whole.get(key), (key, sharded, whole)
        assert sharded["gaussians"] == whole["gaussians"]
        for key in ("correlation", "correlation_log_density", "correlation_rank"):
            assert sharded[key] == pytest.approx(whole[key], abs=1e-4), key
    assert sum(e["cdc_densify"] for e in one["events"]) > 0 and sum(e["cdc_prune"] for e in one["events"]) > 0
    sharded, whole = (load_checkpoint(str(tmp_path / n / "checkpoint.pt"), map_location="cpu") for n in ("two", "one"))
    assert_same_gaussians(sharded["model"]["params"], whole["model"]["params"])
    means, rows = sharded["model"]["params"]["means"], sharded["rows"]
    assert sum(rows) == means.shape[0] and min(rows) > 0
    if iters > 4:
        return
    for piece in (*means.split(rows), whole["model"]["params"]["means"]):
        assert torch.equal(morton_order(piece), torch.arange(piece.shape[0])), "not in Morton order"
    assert not torch.equal(morton_order(means), torch.arange(means.shape[0])), "the slices are sorted apart"


def test_a_sharded_run_stopped_by_a_signal_resumes_sharded(scene, tmp_path):
    """SIGTERM on rank 1 during iteration 4, a log point: both processes stop there, rank 0 writes
    the checkpoint and the PLY of every slice, half-way to the run's one densification (at 8).
    Resumed to 6 on two processes it takes the run that one process resumed from the same
    checkpoint takes, its statistics included (the checkpoint's are summed over the processes
    already, and count once)."""
    import shutil

    common = dict(scene=scene, options={**CLONES, "densify_from": 7, "densify_every": 8}, checkpoint_every=0)
    first = tmp_path / "first"
    r0, r1 = ok(run_ranks("train", 2, tmp_path, timeout=120.0, out=first, stop_at=4, dist_mode="shards", **common))
    assert r0["stopped"] == r1["stopped"] == "SIGTERM" and r0["step"] == r1["step"] == 4
    assert {"save_checkpoint", "write_ply"} <= set(r0["writes"]) and r1["writes"] == []
    ply = read_ply(str(first / "point_cloud.ply"))
    for name in ("two", "one"):
        shutil.copytree(first, tmp_path / name)
    resumed = dict(common, iters=6, resume=True)
    ok(run_ranks("train", 2, tmp_path, timeout=120.0, out=tmp_path / "two", dist_mode="shards", **resumed))
    ok([run_here("train", out=tmp_path / "one", **resumed)])
    stopped, sharded, whole = (
        load_checkpoint(str(tmp_path / name / "checkpoint.pt"), map_location="cpu") for name in ("first", "two", "one")
    )
    assert stopped["step"] == 4 and sharded["step"] == whole["step"] == 6
    assert sum(stopped["rows"]) == stopped["model"]["params"]["means"].shape[0] == ply.means.shape[0]
    statistics = ("grad_sum", "count", "max_radius")
    assert all(stopped["strategy_state"][key].abs().sum() > 0 for key in statistics), "the checkpoint must carry some"
    nearest = assert_same_gaussians(sharded["model"]["params"], whole["model"]["params"])
    for key in statistics:
        torch.testing.assert_close(
            sharded["strategy_state"][key], whole["strategy_state"][key][nearest], rtol=1e-5, atol=1e-9, msg=key
        )


def test_a_process_that_dies_mid_run_stops_the_other(scene, tmp_path):
    """Rank 1 exits after iteration 4 (no log point there: rank 0's next collective is the render's
    exchange): rank 0 fails with RankFailed (the command's exit status 4), not with gloo's own error
    or a wait for the timeout."""
    options = {**SCHEDULE, "densify_from": 20}  # no refinement after 4 either
    r0, r1 = run_ranks(
        "train",
        2,
        tmp_path,
        scene=scene,
        out=tmp_path / "run",
        die_at=4,
        dist_mode="shards",
        log_every=12,
        options=options,
    )
    assert r1["exitcode"] == 17
    assert r0.get("error") == "RankFailed", r0
    assert r0["seconds"] < 25


def test_the_timed_steps_exchanges_are_measured(scene, tmp_path):
    """22 views two at a time: step 10 (iterations 21 and 22) is the timed one, as in data
    parallelism; its exchanges' waits and transfers are parts of its time, and the bytes are the
    slices' fields both ways."""
    ok(run_ranks("train", 2, tmp_path, timeout=120.0, scene=scene, out=tmp_path / "run", iters=22, dist_mode="shards"))
    with open(tmp_path / "run" / "metrics.json") as f:
        metrics = json.load(f)
    comm = metrics["communication"]
    assert (comm["timed_steps"], comm["backend"], len(comm["per_process"])) == (1, "gloo", 2), comm
    total = metrics["num_gaussians"]
    for own, rows in zip(comm["per_process"], metrics["rows"]):
        assert own["exchanged_by"] == "the sharded render's point-to-point transfers"
        assert own["wait_ms_per_step"] > 0 and 0 < own["all_reduce_ms_per_step"] < own["step_ms"], own
        assert own["all_reduce_bytes_per_step"] == (rows + (total - rows)) * 88  # one round, two processes
    assert comm["share"] == pytest.approx(comm["all_reduce_ms_per_step"] / comm["step_ms"])


def test_replayed_sharded_steps_are_the_eager_ones(scene, tmp_path):
    """40 iterations of two views a step on two slices: the steps replayed from graphs (on the CPU
    the same body, one operation at a time), with slots of exactly each view's last count so that
    renders of grown Gaussians overflow them and both processes go back together (reading the
    device every 10 iterations: a halt holds back the steps after it, and a rewind picks among
    several steps' snapshots), train the bits of the steps that read every count."""
    runs = {}
    for name, options in (("eager", {}), ("replayed", {"cuda_graph": True, "tight_slots": True})):
        common = dict(scene=scene, out=tmp_path / name, iters=40, dist_mode="shards", timeout=120.0, log_every=10)
        runs[name] = ok(run_ranks("train", 2, tmp_path, **common, **options))
    for eager, replayed in zip(runs["eager"], runs["replayed"]):
        assert eager["cuda_graph"]["off"].startswith("--cuda-graph replays steps on CUDA")
        assert replayed["cuda_graph"]["replayed_steps"] > 0, replayed["cuda_graph"]
        assert replayed["sync_free"]["rewinds"] > 0, replayed["sync_free"]
        # each iteration's parameters as last taken (the steps taken again after a rewind replace theirs)
        assert dict(replayed["checksums"]) == dict(eager["checksums"])
        assert len(dict(eager["checksums"])) == 20
    assert runs["replayed"][0]["sync_free"] == runs["replayed"][1]["sync_free"]
    assert runs["replayed"][0]["cuda_graph"]["replayed_steps"] == runs["replayed"][1]["cuda_graph"]["replayed_steps"]


@pytest.mark.skipif(
    not torch.cuda.is_available() or torch.cuda.device_count() < 2 or not torch.distributed.is_nccl_available(),
    reason="needs two GPUs and NCCL",
)
def test_two_slices_on_two_gpus_train_as_one_gpu(scene, tmp_path, device):
    """The same on two GPUs (NCCL): as close as CUDA's atomic sums let two runs be."""
    if device == "cpu":
        pytest.skip("NCCL on two GPUs (the CPU case is the test above)")
    options = {**SCHEDULE, "clone_max_scale": 1e9}
    gpus = dict(scene=scene, options=options, checkpoint_every=0, device="cuda", dist_backend="auto")
    r0, r1 = ok(run_ranks("train", 2, tmp_path, timeout=300.0, out=tmp_path / "two", dist_mode="shards", **gpus))
    one = ok([run_here("train", out=tmp_path / "one", **gpus)])[0]
    assert [e["step"] for e in r0["events"]] == [e["step"] for e in one["events"]] == [4, 8]
    assert r0["metrics"]["num_gaussians"] == pytest.approx(one["metrics"]["num_gaussians"], rel=0.05)
    assert r0["params"]["means"].shape[0] + r1["params"]["means"].shape[0] == r0["metrics"]["num_gaussians"]
    assert r0["test"]["psnr"] == pytest.approx(one["test"]["psnr"], abs=0.3)
    assert r0["cuda_graph"]["replayed_steps"] == r1["cuda_graph"]["replayed_steps"] > 0, r0["cuda_graph"]


def test_refusals_name_the_option():
    config = task_config("scene", "out", dist_mode="shards")
    assert "two or more" in shard_refusal(config, 1)
    assert shard_refusal(config, 2) is None
    assert shard_refusal(config, 2, make_strategy("3dgs", {})) is None
    assert shard_refusal(config, 2, make_strategy("absgs", {})) is None
    assert shard_refusal(task_config("s", "o", strategy="cdc"), 2, make_strategy("cdc", {})) is None
    online = make_strategy("cdc", {"complexity_schedule": "online"})
    assert "--complexity-schedule online" in shard_refusal(task_config("s", "o", strategy="cdc"), 2, online)
    assert "relocates" in shard_refusal(config, 2, make_strategy("mcmc", {}))
    assert "--target-gaussians" in shard_refusal(config, 2, make_strategy("3dgs", {"target_gaussians": 100}))
    assert "--budget-schedule" in shard_refusal(config, 2, make_strategy("fast", {}))
    for order in ("appended", "morton", "auto"):  # morton sorts each process's own slice
        assert shard_refusal(config, 2, make_strategy("3dgs", {"gaussian_order": order})) is None
    assert shard_refusal(task_config("s", "o", sync_free=True, cuda_graph=True), 2) is None
    assert "selective" in shard_refusal(task_config("s", "o", optimizer="selective"), 2)
    assert "--dist-exchange" in shard_refusal(task_config("s", "o", dist_exchange="colours"), 2)
    assert "--resolution-schedule" in shard_refusal(task_config("s", "o", resolution_schedule="dash"), 2)


def test_the_configurations_mode_picks_the_trainer():
    assert type(Trainer(task_config("s", "o"))) is Trainer
    assert type(Trainer(task_config("s", "o", dist_mode="shards"))) is ShardedTrainer
    assert type(Trainer.__new__(Trainer)) is Trainer  # a bare one, as tests make

    class Mine(Trainer):
        pass

    with pytest.raises(OptionError, match="Mine trains --dist-mode data, not shards"):
        Mine(task_config("s", "o", dist_mode="shards"))


def test_one_process_is_refused_before_the_scene_loads(tmp_path, monkeypatch):
    monkeypatch.setenv("NCCL_GRAPH_REGISTER", "unset below")  # so that the test's end removes what run() sets
    monkeypatch.delenv("NCCL_GRAPH_REGISTER")
    trainer = Trainer(task_config(tmp_path / "no_scene", tmp_path / "out", dist_mode="shards"), dict(SCHEDULE))
    assert isinstance(trainer, ShardedTrainer)
    with pytest.raises(OptionError, match="two or more"):
        trainer.run()
    # set before the process group's communicator starts: NCCL's registration of captured buffers off
    assert os.environ["NCCL_GRAPH_REGISTER"] == "0"


def test_nccl_registering_captured_buffers_refuses_the_replayed_steps(monkeypatch, capsys):
    """A launch that sets NCCL_GRAPH_REGISTER on: --cuda-graph is refused naming it, the default
    trains without graphs and says why (on a GPU; the CPU replays nothing anyway)."""
    monkeypatch.setenv("NCCL_GRAPH_REGISTER", "1")
    trainer = Trainer.__new__(ShardedTrainer)
    trainer.device = torch.device("cuda", 0)
    trainer.ranks = type("Ranks", (), {"is_main": True})()
    trainer.config = task_config("s", "o", dist_mode="shards", cuda_graph=True)
    with pytest.raises(OptionError, match="NCCL_GRAPH_REGISTER=1"):
        trainer._graph_steps()
    trainer.config = task_config("s", "o", dist_mode="shards")
    assert trainer._graph_steps() is None
    assert "NCCL_GRAPH_REGISTER=1" in trainer.graph_off
    assert "steps run without CUDA graphs" in capsys.readouterr().out


def test_even_rows():
    assert even_rows(10, 3) == [4, 3, 3]
    assert even_rows(2, 4) == [1, 1, 0, 0]
    assert sum(even_rows(12345, 7)) == 12345
