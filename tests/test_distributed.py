"""Data-parallel training (cdcgs.train.distributed) on the CPU with gloo, and batches of views in
one process: 2 processes of a scene of 32 x 32 views and a few dozen Gaussians against one."""

import json
import math
import os
import subprocess
import sys

import pytest
import torch
from dist_tasks import SCHEDULE, first_step_gradients, ok, run_here, run_ranks, task_config
from helpers import hand_model

from cdcgs.datasets.procedural import make_procedural_scene
from cdcgs.errors import OptionError
from cdcgs.train import ops
from cdcgs.train.config import LearningRates, TrainConfig, batch_rule
from cdcgs.train.distributed import balanced_positions, choose_backend, my_positions, splits_by_counts, step_seed
from cdcgs.train.trainer import Trainer, crossed

pytestmark = pytest.mark.skipif(
    not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
    reason="this torch has no torch.distributed with gloo",
)

MCMC_SCHEDULE = {"refine_from": 2, "refine_every": 4, "refine_until": 10, "target_gaussians": 80}


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    """9 views of 32 x 32 pixels (6 for training, 3 held out) and 48 points."""
    return make_procedural_scene(tmp_path_factory.mktemp("dist_scene"), views=9, width=32, height=32, points=48)


def assert_params_close(a, b, rtol=1e-5, atol=1e-6):
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].shape == b[name].shape, name
        torch.testing.assert_close(a[name], b[name], rtol=rtol, atol=atol, msg=name)


@pytest.fixture(scope="module")
def runs_3dgs(small_scene, tmp_path_factory):
    """The same 12-iteration run (batch 2, densification at 4 and 8, a reset at 8) on 2 processes and on 1."""
    tmp = tmp_path_factory.mktemp("runs_3dgs")
    two = ok(run_ranks("train", 2, tmp, scene=small_scene, out=tmp / "two"))
    one = ok([run_here("train", scene=small_scene, out=tmp / "one")])[0]
    return two, one, tmp


def test_two_processes_sum_the_gradients_of_one_batch(small_scene, tmp_path):
    ranks = ok(run_ranks("first_step_gradients", 2, tmp_path, scene=small_scene, out=tmp_path / "two"))
    one = first_step_gradients(rank=0, world=1, scene=small_scene, out=tmp_path / "one")
    for name in one:
        assert torch.equal(ranks[0][name], ranks[1][name]), name
        torch.testing.assert_close(ranks[0][name], one[name], rtol=1e-5, atol=1e-9, msg=name)
    assert any(g.abs().max() > 0 for g in one.values())


@pytest.mark.parametrize("batch", [2, 3])
def test_exchanging_colours_gives_the_gradients_of_one_batch(small_scene, tmp_path, batch):
    """--dist-exchange colours: the spherical harmonics' gradients rebuilt on every process from the
    views' colour gradients equal one process's batch gradients (rtol 1e-5), the same bits on both
    processes; with 3 views on 2 processes one process renders 2 and the other 1 (zeros padded)."""
    colours = dict(scene=small_scene, batch_size=batch, dist_exchange="colours", sh_degree=3)
    ranks = ok(run_ranks("first_step_gradients", 2, tmp_path, out=tmp_path / "two", **colours))
    one = first_step_gradients(rank=0, world=1, scene=small_scene, out=tmp_path / "one", batch_size=batch, sh_degree=3)
    for name in one:
        assert torch.equal(ranks[0][name], ranks[1][name]), name
        torch.testing.assert_close(ranks[0][name], one[name], rtol=1e-5, atol=1e-9, msg=name)
    assert one["sh_dc"].abs().max() > 0 and one["sh_rest"].abs().max() > 0


@pytest.mark.parametrize("options", [{}, {"cuda_graph": True}], ids=["eager", "replayed"])
def test_runs_that_exchange_colours_stay_equal_and_match_one_process(small_scene, runs_3dgs, tmp_path, options):
    """A whole run with --dist-exchange colours (densification, an opacity reset, SH degrees 0 to 2):
    the processes equal after every step, and the run that of one process, as close as with the
    gradients exchanged; the replayed steps give the eager ones' bits."""
    _, one, _ = runs_3dgs
    two = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "two", dist_exchange="colours", **options)
    r0, r1 = ok(two)
    assert r0["checksums"] == r1["checksums"]
    assert [e["step"] for e in r0["events"]] == [e["step"] for e in one["events"]]
    assert_params_close(r0["params"], one["params"])
    if options:
        eager = ok(run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "eager", dist_exchange="colours"))[
            0
        ]
        assert r0["cuda_graph"]["replayed_steps"] > 0
        assert r0["checksums"] == eager["checksums"]


def test_two_processes_on_one_gpu_with_gloo_sum_the_gradients(small_scene, tmp_path, device):
    """The CUDA path of gloo (several processes sharing a GPU): gloo reduces host copies. Reducing
    the CUDA tensors directly trained to 10 dB on bonsai (H100, 2026-11-25) with equal ranks."""
    if device == "cpu":
        pytest.skip("the CPU case is test_two_processes_sum_the_gradients_of_one_batch")
    gpu = dict(scene=small_scene, device="cuda:0", backend="gloo")
    ranks = ok(run_ranks("first_step_gradients", 2, tmp_path, out=tmp_path / "two", **gpu))
    one = first_step_gradients(rank=0, world=1, out=tmp_path / "one", **gpu)
    for name in one:
        assert torch.equal(ranks[0][name], ranks[1][name]), name
        scale = float(one[name].abs().max())
        torch.testing.assert_close(ranks[0][name], one[name], rtol=1e-4, atol=1e-6 * scale, msg=name)
    assert any(g.abs().max() > 0 for g in one.values())


def test_ranks_stay_equal_and_match_one_process(runs_3dgs):
    (r0, r1), one, _ = runs_3dgs
    assert [s for s, _ in r0["checksums"]] == list(range(2, 13, 2))
    assert r0["checksums"] == r1["checksums"], "the ranks' parameters differ after some step"
    kinds = {key for event in r0["events"] for key in event}
    assert {"cloned", "split", "opacity_reset"} <= kinds, "the run must densify and reset"
    assert [e["step"] for e in r0["events"]] == [e["step"] for e in one["events"]] == [4, 8]
    assert r0["metrics"] == {**one["metrics"], "processes": 2}
    assert_params_close(r0["params"], one["params"])
    assert r0["test"]["views"] == one["test"]["views"] == 3
    assert r0["test"]["psnr"] == pytest.approx(one["test"]["psnr"], abs=1e-3)


def test_only_rank_0_writes(runs_3dgs):
    (r0, r1), _, tmp = runs_3dgs
    assert r1["writes"] == []
    assert {"save_checkpoint", "write_ply", "write_json"} <= set(r0["writes"])
    folder = tmp / "two"
    assert len(os.listdir(folder / "test_renders")) == 3, "every test view's picture, written by rank 0"
    assert json.loads((folder / "config.json").read_text())["processes"] == 2
    state = torch.load(folder / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert (state["processes"], state["batch_size"]) == (2, 2)


@pytest.mark.parametrize(
    "strategy, options, replayed",
    [
        ("cdc", {**SCHEDULE, "periodic_prune_every": 8}, False),
        ("cdc", {**SCHEDULE, "complexity_schedule": "online", "view_aggregation": "mean"}, False),
        ("mcmc", MCMC_SCHEDULE, False),
        ("mcmc", MCMC_SCHEDULE, True),
        ("cdc", {**SCHEDULE, "periodic_prune_every": 8}, True),
    ],
    ids=["cdc", "cdc-online-mean", "mcmc", "mcmc-replayed", "cdc-replayed"],
)
def test_strategies_stay_equal_across_ranks(small_scene, tmp_path, strategy, options, replayed):
    """CDC's Γ pass split over the ranks, its online statistics reduced, MCMC's draws seeded by step
    (the two processes' MCMC steps replayed, its noise drawn after each replay on every process,
    against one process without them; CDC's replayed, each process's share of a Γ pass measured
    in groups from one body, GammaGroups)."""
    extra = {"cuda_graph": True} if replayed else {}
    r0, r1 = ok(
        run_ranks(
            "train", 2, tmp_path, scene=small_scene, out=tmp_path / "two", strategy=strategy, options=options, **extra
        )
    )
    one = ok([run_here("train", scene=small_scene, out=tmp_path / "one", strategy=strategy, options=options)])[0]
    assert r0["checksums"] == r1["checksums"]
    if replayed:
        counts = [r["cuda_graph"]["replayed_steps"] for r in (r0, r1)]
        assert counts[0] == counts[1] > 0, counts
        if strategy == "cdc":
            assert all(r["cuda_graph"]["gamma_groups"] > 0 for r in (r0, r1)), [r["cuda_graph"] for r in (r0, r1)]
    assert [e["step"] for e in r0["events"]] == [e["step"] for e in one["events"]] and r0["events"]
    assert_params_close(r0["params"], one["params"], rtol=1e-4, atol=1e-5)


LONGER = 40  # iterations: enough for renders of grown Gaussians to overflow slots of their last count


@pytest.fixture(scope="module")
def counted_longer(small_scene, tmp_path_factory):
    """Rank 0 of a 2-process run of LONGER iterations that reads every count."""
    tmp = tmp_path_factory.mktemp("counted_longer")
    return ok(run_ranks("train", 2, tmp, scene=small_scene, out=tmp / "two", iters=LONGER))[0]


@pytest.mark.parametrize(
    "options",
    [
        {"sync_free": True, "tight_slots": True},
        {"cuda_graph": True},
        {"cuda_graph": True, "tight_slots": True},
    ],
    ids=["sync-free-slots-of-the-last-count", "replayed", "replayed-slots-of-the-last-count"],
)
def test_steps_that_read_no_count_on_two_processes_are_the_run_that_reads_every_count(
    small_scene, counted_longer, tmp_path, options
):
    """--sync-free and the replayed steps on two processes: a halt of either process (its slots
    overflowed) travels with the step's all-reduce, stops every update on both, and both go back
    to the same iteration at the next read; the replayed steps hold the all-reduce and are taken
    by both processes or by neither. Either way the run is the one that reads every count, bit
    for bit, with the processes equal after every step."""
    counted = counted_longer
    two = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "two", iters=LONGER, **options)
    r0, r1 = ok(two)
    assert r0["checksums"] == r1["checksums"]
    assert r0["checksums"][-1] == counted["checksums"][-1]
    for name, value in counted["params"].items():
        assert torch.equal(r0["params"][name], value), name
    summaries = [r["sync_free"] for r in (r0, r1)]
    if options.get("tight_slots"):
        assert all(s["rewinds"] > 0 for s in summaries), summaries  # every process went back
        assert summaries[0]["rewinds"] == summaries[1]["rewinds"], summaries
    if options.get("cuda_graph"):
        replayed = [r["cuda_graph"]["replayed_steps"] for r in (r0, r1)]
        assert replayed[0] == replayed[1] > 0, replayed
        # A graph that holds NCCL's all-reduce must go before the process group: 2-GPU runs whose
        # last steps were replayed hung at its destruction (2 x H200, 2026-11-27).
        assert r0["released_before_close"] == r1["released_before_close"] == [True]
        # One buffer for the reduced flags: a replayed step writes the one the host reads.
        assert r0["flag_buffers"] == r1["flag_buffers"] == 1


def test_a_refusal_of_the_replayed_steps_on_one_process_holds_for_all(small_scene, runs_3dgs, tmp_path):
    """Rank 0 alone has a callback that renders beside the training (the viewer), which refuses the
    replayed steps there; the others would take them (here on the CPU as on CUDA). A replayed step
    holds the all-reduce, which every process must replay together: all train without them, as the
    run that reads every count, and say why."""
    (counted, _), _, _ = runs_3dgs
    r0, r1 = ok(run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "two", viewer_on_rank_0=True))
    assert r0["checksums"] == r1["checksums"] == counted["checksums"]
    assert "drop --view" in r0["cuda_graph"]["off"], r0["cuda_graph"]
    assert "drop --view (on process 0, so on every process)" in r1["cuda_graph"]["off"], r1["cuda_graph"]
    assert r0["sync_free"] is None and r1["sync_free"] is None


def test_the_replayed_steps_refuse_gloo_on_a_gpu(monkeypatch):
    """A replayed step captures its all-reduce, which gloo (host memory) cannot take part in.
    Stand-ins for Warp's device and memory pool, so this runs on the CPU."""
    from types import SimpleNamespace

    import warp as wp

    from cdcgs.train import graph
    from cdcgs.train.distributed import Ranks
    from cdcgs.train.graph import graph_refusal

    monkeypatch.setattr(graph, "warp_device", lambda device: "cuda:0")
    monkeypatch.setattr(wp, "is_mempool_supported", lambda device: True)

    trainer = SimpleNamespace(
        config=TrainConfig(batch_size=2), device=torch.device("cuda", 0), ranks=Ranks(0, 2, "gloo")
    )
    why, what = graph_refusal(trainer)
    assert "gloo" in why and "NCCL" in what


@pytest.mark.skipif(
    not torch.cuda.is_available() or torch.cuda.device_count() < 2 or not torch.distributed.is_nccl_available(),
    reason="needs two GPUs and NCCL",
)
def test_replayed_steps_on_two_gpus_hold_the_all_reduce_and_keep_the_ranks_equal(small_scene, tmp_path, device):
    """NCCL's all-reduce captured in each process's graph: the processes replay together, stay
    equal after every step, train as the run that reads every count does (as close as CUDA's
    atomic sums let two runs be), and end (the graphs go before the process group)."""
    if device == "cpu":
        pytest.skip("NCCL on two GPUs (the CPU case is the test above)")
    gpus = dict(scene=small_scene, iters=LONGER, device="cuda", dist_backend="auto", timeout=300.0)
    replayed = ok(run_ranks("train", 2, tmp_path, out=tmp_path / "replayed", cuda_graph=True, **gpus))
    counted = ok(run_ranks("train", 2, tmp_path, out=tmp_path / "counted", cuda_graph=False, **gpus))
    assert replayed[0]["checksums"] == replayed[1]["checksums"]
    assert replayed[0]["cuda_graph"]["replayed_steps"] > 0, replayed[0]["cuda_graph"]
    assert replayed[0]["released_before_close"] == [True]
    assert replayed[0]["metrics"]["num_gaussians"] == pytest.approx(counted[0]["metrics"]["num_gaussians"], rel=0.05)
    assert replayed[0]["test"]["psnr"] == pytest.approx(counted[0]["test"]["psnr"], abs=0.3)


def test_a_stopped_run_on_two_processes_resumes_in_one(small_scene, runs_3dgs):
    (whole, _), _, tmp = runs_3dgs
    out = tmp / "stopped"
    stopped = ok(run_ranks("train", 2, tmp, scene=small_scene, out=out, stop_at=5))
    # Rank 1 alone got the signal, after the step to iteration 6; its flag travels with the next
    # step's all-reduce, and both stop at the log point after it (iteration 8).
    assert [s["step"] for s in stopped] == [8, 8] and all("stopped" in s for s in stopped)
    resumed = ok([run_here("train", scene=small_scene, out=out, resume=True)])[0]
    assert resumed["checksums"][0][0] == 10
    assert_params_close(resumed["params"], whole["params"])


def test_a_run_of_one_process_resumes_on_two(small_scene, runs_3dgs):
    _, whole, tmp = runs_3dgs
    out = tmp / "stopped_one"
    ok(run_ranks("train", 1, tmp, scene=small_scene, out=out, stop_at=3))
    r0, r1 = ok(run_ranks("train", 2, tmp, scene=small_scene, out=out, resume=True))
    assert r0["checksums"] == r1["checksums"] and r0["checksums"][0][0] == 6
    assert_params_close(r0["params"], whole["params"])


def test_a_dead_rank_stops_the_others(small_scene, tmp_path):
    r0, r1 = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "run", die_at=4)
    assert r1["exitcode"] == 17
    assert r0.get("error") == "RankFailed", r0
    assert r0["seconds"] < 25


def test_a_failed_setup_stops_every_rank_with_the_cause(small_scene, tmp_path):
    r0, r1 = run_ranks("failing_setup", 2, tmp_path, scene=small_scene, out=tmp_path / "run")
    assert r1.get("error") == "InputError"
    assert r0.get("error") == "RankFailed" and "rank 1" in r0["message"] and "unreadable" in r0["message"]
    assert r0["seconds"] < 25
    assert not (tmp_path / "run").exists(), "the folder rank 0 made is removed again"


def test_lpips_missing_on_one_process_is_left_out_on_every_one(small_scene, tmp_path):
    """Each process looks for the LPIPS weights itself; the evaluation is split over them. A network
    that one process lacks is scored by none (not over some views only), and the note names it."""
    outs = run_ranks("lpips_agreement", 2, tmp_path, scene=small_scene, out=tmp_path / "run")
    assert all("result" in o for o in outs), outs
    first, second = (o["result"] for o in outs)
    assert first["lpips_vgg"] is None and second["lpips_vgg"] is None
    assert first["lpips_alex"] is not None and first["lpips_alex"] == second["lpips_alex"]
    note = first["lpips_note"]
    assert "LPIPS-vgg not scored" in note and "process 1: LPIPS-vgg: its weights are not in" in note, note
    assert "process 0" not in note and "LPIPS-alex" not in note


def test_ranks_that_drift_apart_stop(small_scene, tmp_path):
    outs = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "run", perturb_at=4, check_ranks_every=6)
    assert [o.get("error") for o in outs] == ["RankDrift", "RankDrift"], outs
    assert "iteration 6" in outs[0]["message"]


def test_replayed_steps_of_two_views_per_process_are_the_eager_ones(small_scene, tmp_path):
    """Batches of 4 on two processes: each replays its two views in one graph with the step's
    all-reduce, and trains the eager steps' bits; a batch that the processes do not divide is
    refused by --cuda-graph, naming the option."""
    runs = {}
    for name, options in (("eager", {}), ("graph", {"cuda_graph": True})):
        two = run_ranks(
            "train", 2, tmp_path, scene=small_scene, out=tmp_path / name, iters=LONGER, batch_size=4, **options
        )
        runs[name] = ok(two)
    eager, replayed = runs["eager"], runs["graph"]
    assert replayed[0]["checksums"] == replayed[1]["checksums"] == eager[0]["checksums"]
    assert replayed[0]["cuda_graph"]["replayed_steps"] == replayed[1]["cuda_graph"]["replayed_steps"] > 0
    outs = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "odd", batch_size=3, cuda_graph=True)
    assert [o.get("error") for o in outs] == ["OptionError", "OptionError"], outs
    assert "--batch-size that 2 processes divide, not 3" in outs[0]["message"]


def test_views_split_by_their_counts_are_the_batch_of_one_process(small_scene, tmp_path, capsys):
    """--dist-balance counts, batches of 4 on two processes: once the counts are agreed, each step's
    views are split by them (every position rendered by one process, two each; some steps not in
    the default split), the eager steps (--sync-free) and the replayed ones train the same bits on
    both processes, also where renders overflow their slots and the processes go back, and the run
    is the one-process batch of 4 within float rounding (the same views and gradients, summed in
    another order). One process says that it has nothing to split; with --dist-exchange colours
    the option is refused."""
    runs = {}
    ways = {
        "eager": {"sync_free": True},
        "graph": {"cuda_graph": True},
        "tight": {"sync_free": True, "tight_slots": True},
    }
    for name, options in ways.items():
        two = run_ranks(
            "train",
            2,
            tmp_path,
            scene=small_scene,
            out=tmp_path / name,
            iters=LONGER,
            batch_size=4,
            dist_balance="counts",
            **options,
        )
        runs[name] = ok(two)
    capsys.readouterr()
    one = run_here(
        "train",
        scene=small_scene,
        out=tmp_path / "one",
        iters=LONGER,
        batch_size=4,
        sync_free=True,
        dist_balance="counts",  # one process: nothing to split, and it says so
    )
    one = ok([one])[0]
    assert "--dist-balance counts: one process; the views split by position" in capsys.readouterr().out
    assert one["dist_balance"] == {"mode": "counts", "balanced_steps": 0}
    for r0, r1 in runs.values():
        assert r0["checksums"] == r1["checksums"]
        assert r0["dist_balance"]["balanced_steps"] == r1["dist_balance"]["balanced_steps"] > 0
        moved = 0
        for (first, mine, costs), (other_first, theirs, other_costs) in zip(r0["splits"], r1["splits"]):
            assert first == other_first and costs == other_costs
            assert sorted(mine + theirs) == [0, 1, 2, 3] and len(mine) == 2
            moved += mine != my_positions(4, 0, 2)
            if costs is not None and None not in costs:  # the views' own costs, at least as even as by position
                largest = max(sum(costs[p] for p in mine), sum(costs[p] for p in theirs))
                assert largest <= max(sum(costs[p] for p in my_positions(4, r, 2)) for r in (0, 1))
        assert moved > 0, "no step left the default split"
        assert [e["step"] for e in r0["events"]] == [e["step"] for e in one["events"]]
        # 40 iterations of Adam carry the sums' rounding further than 12 do: the default split
        # itself ends 7.5e-6 from one process in the quaternions here, this one 1.7e-5
        assert_params_close(r0["params"], one["params"], rtol=1e-4, atol=1e-4)
    assert runs["eager"][0]["checksums"] == runs["graph"][0]["checksums"]
    assert runs["graph"][0]["cuda_graph"]["replayed_steps"] > 0
    # Renders that overflow their slots: both processes go back together and split the steps
    # taken again by the counts they then agree on.
    rewinds = [r["sync_free"]["rewinds"] for r in runs["tight"]]
    assert rewinds[0] == rewinds[1] > 0
    # refused at set-up on any number of processes: checked here, without starting two
    out = run_here(
        "train",
        scene=small_scene,
        out=tmp_path / "colours",
        batch_size=4,
        dist_balance="counts",
        dist_exchange="colours",
    )
    assert out.get("error") == "OptionError", out
    assert "--dist-balance counts" in out["message"] and "--dist-exchange colours" in out["message"]


def test_the_split_by_counts_pairs_the_costliest_with_the_cheapest():
    """balanced_positions: every position to one process, the same share each, the same split on
    every process; two views a process: the split of least largest load (brute force over all
    splits); ties by position; a batch the processes do not divide is refused."""
    import random

    def pairings(items):  # every split of ``items`` into pairs
        if not items:
            yield []
            return
        first, rest = items[0], items[1:]
        for k, partner in enumerate(rest):
            for others in pairings(rest[:k] + rest[k + 1 :]):
                yield [(first, partner), *others]

    rng = random.Random(3)
    for world, share in ((2, 2), (2, 3), (3, 2), (4, 2), (2, 5)):
        batch = world * share
        for turn in range(30):
            costs = [rng.randint(1, 1000) for _ in range(batch)]
            split = [balanced_positions(costs, rank, world, turn) for rank in range(world)]
            assert sorted(p for mine in split for p in mine) == list(range(batch))
            assert all(len(mine) == share and mine == sorted(mine) for mine in split)
            if share == 2:  # the split of least largest load, by brute force over every pairing
                largest = max(sum(costs[p] for p in mine) for mine in split)
                best = min(max(costs[a] + costs[b] for a, b in pairs) for pairs in pairings(list(range(batch))))
                assert largest == best, (costs, split)
    # 9 with 1 and 5 with 3; the costliest view to rank ``turn`` (mod the processes); ties go to
    # the earlier position
    assert [balanced_positions([5, 1, 9, 3], rank, 2) for rank in (0, 1)] == [[1, 2], [0, 3]]
    assert [balanced_positions([5, 1, 9, 3], rank, 2, turn=1) for rank in (0, 1)] == [[0, 3], [1, 2]]
    assert [balanced_positions([2, 2, 2, 2], rank, 2) for rank in (0, 1)] == [[0, 2], [1, 3]]
    assert [balanced_positions([2, 2, 2, 2], rank, 2, turn=3) for rank in (0, 1)] == [[1, 3], [0, 2]]
    assert [balanced_positions([7, 1, 4, 2, 9, 3], rank, 3, turn=2) for rank in (0, 1, 2)] == [[0, 3], [2, 5], [1, 4]]
    with pytest.raises(ValueError, match="does not split evenly"):
        balanced_positions([1, 2, 3], 0, 2)
    # what --dist-balance counts splits: a multiple of the processes, two views or more each
    assert [splits_by_counts(count, 2) for count in (2, 3, 4, 5, 6)] == [False, False, True, False, True]
    assert [splits_by_counts(count, 3) for count in (3, 6, 8, 9)] == [False, True, False, True]


def test_a_batch_smaller_than_the_processes_is_refused(small_scene, tmp_path):
    outs = run_ranks("train", 2, tmp_path, scene=small_scene, out=tmp_path / "run", batch_size=1)
    assert [o.get("error") for o in outs] == ["OptionError", "OptionError"]
    assert "--batch-size 1" in outs[0]["message"]


def test_ranks_take_the_callers_environment_and_directory_of_the_moment(tmp_path, monkeypatch):
    """The tests' ranks fork from a fork server that keeps the environment of the session's first
    launch: each launch still hands its ranks the caller's environment and working directory as
    they are then (a variable set, one removed, a new directory), and each rank is a new process."""
    ok(run_ranks("surroundings", 2, tmp_path, names=[]))  # the fork server runs from here on
    monkeypatch.setenv("CDCGS_TEST_SET_LATER", "later")
    monkeypatch.delenv("HOME", raising=False)
    monkeypatch.chdir(tmp_path)
    first, second = ok(run_ranks("surroundings", 2, tmp_path, names=["CDCGS_TEST_SET_LATER", "HOME"]))
    for rank, seen in enumerate((first, second)):
        assert seen["environment"] == {"CDCGS_TEST_SET_LATER": "later", "HOME": None}
        assert seen["cwd"] == str(tmp_path) and seen["rank"] == (str(rank), "2")
        assert seen["pid"] != os.getpid() and not seen["warp_runtime"]
    assert first["pid"] != second["pid"]


def test_torchrun_launches_the_command_line(small_scene, tmp_path):
    out = tmp_path / "run"
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "cdcgs"]
    # 22 views at batch 2: steps 0 … 10, and step 10 is the one whose communication is timed
    command += ["train", "--data", str(small_scene), "--out", str(out), "--iters", "22", "--batch-size", "2"]
    command += ["--device", "cpu", "--no-progress", "--test-every", "3", "--eval-every", "20"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    printed = done.stdout + done.stderr
    assert printed.count("outputs in") == 1 and printed.count("[20] test PSNR") == 1, "only rank 0 prints"
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["processes"], metrics["batch_size"], metrics["iterations"]) == (2, 2, 22)
    comm = metrics["communication"]
    assert (comm["timed_steps"], comm["backend"], len(comm["per_process"])) == (1, "gloo", 2), comm
    for key in ("wait_ms_per_step", "all_reduce_ms_per_step", "all_reduce_bytes_per_step", "step_ms"):
        assert comm[key] == pytest.approx(sum(p[key] for p in comm["per_process"]) / 2)
    for own in comm["per_process"]:
        assert own["wait_ms_per_step"] > 0 and 0 < own["all_reduce_ms_per_step"] < own["step_ms"], own
    assert comm["share"] == pytest.approx(comm["all_reduce_ms_per_step"] / comm["step_ms"])
    assert comm["wait_share"] == pytest.approx(comm["wait_ms_per_step"] / comm["step_ms"])
    # the flat buffer: every Gaussian's 59 gradients, the statistics' additions and the two flags
    sizes = {p["all_reduce_bytes_per_step"] for p in comm["per_process"]}
    assert len(sizes) == 1 and sizes.pop() >= 4 * (59 * metrics["num_gaussians"] + 2)
    rate = comm["all_reduce_bytes_per_step"] / comm["all_reduce_ms_per_step"] / 1e6
    assert comm["all_reduce_gb_per_second"] == pytest.approx(rate)


@pytest.mark.parametrize("world", ["1", "2"])
def test_a_process_ends_with_its_status_and_its_output_flushed(tmp_path, world):
    """cdcgs's exit: in a torchrun process (WORLD_SIZE above 1) without the interpreter's shutdown,
    which could abort on gloo's worker thread, but with the status main returned and every line
    written, also those still in a buffer or a logging handler."""
    script = (
        "import atexit, logging, sys\n"
        "from cdcgs.cli import exit_process\n"
        "atexit.register(lambda: sys.stderr.write('shut down'))\n"
        "logging.basicConfig(filename=sys.argv[1], level=logging.INFO)\n"
        "logging.info('logged')\n"
        "sys.stdout.write('no newline, still in the buffer')\n"
        "exit_process(3)\n"
        "print('never')\n"
    )
    log = tmp_path / "log.txt"
    environment = {**os.environ, "WORLD_SIZE": world}
    done = subprocess.run(
        [sys.executable, "-c", script, str(log)], capture_output=True, text=True, timeout=120, env=environment
    )
    assert done.returncode == 3, done.stderr[-2000:]
    assert done.stdout == "no newline, still in the buffer"
    assert "logged" in log.read_text()
    assert ("shut down" in done.stderr) == (world == "1"), "the interpreter's shutdown only in one process"


# ------------------------------------------------------------------------- one process, batches


def small_config(scene, out, **overrides):
    """One process: the tasks' configuration with one view per step unless told otherwise."""
    return task_config(scene, out, **{"batch_size": 1, "log_every": 50, **overrides})


def test_a_batch_gradient_is_the_mean_of_its_views(small_scene, tmp_path):
    from cdcgs.train.loss import fused_photometric_loss

    trainer = Trainer(small_config(small_scene, tmp_path, batch_size=3), dict(SCHEDULE))
    trainer._setup()
    queue, state = list(trainer.view_queue), trainer.view_generator.get_state()
    views = [trainer._next_view() for _ in range(3)]
    trainer.view_queue = queue
    trainer.view_generator.set_state(state)
    params = [g["params"][0] for g in trainer.optimizer.param_groups]
    expected = [torch.zeros_like(p) for p in params]
    for index in views:
        image, _, _ = trainer._render(index)
        loss, _ = fused_photometric_loss(image, trainer.scene.train[index].image, trainer.config.ssim_weight)
        for e, g in zip(expected, torch.autograd.grad(loss, params)):
            e += g / 3
    steps = spy_on_adam(trainer, params)
    trainer.train_step()
    assert trainer.step == 3
    # FusedAdam takes the views' sums and the division by the batch in its rates (gradient_scale)
    assert [scale for scale, _ in steps] == [1.0 / 3]
    for got, want, group in zip(steps[0][1], expected, trainer.optimizer.param_groups):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-9, msg=group["name"])
    # torch's Adam takes no scale: it is given the mean
    config = small_config(small_scene, tmp_path / "torch", batch_size=3, optimizer="torch-adam")
    trainer = Trainer(config, dict(SCHEDULE))
    trainer._setup()
    params = [g["params"][0] for g in trainer.optimizer.param_groups]
    steps = spy_on_adam(trainer, params)
    trainer.train_step()
    assert [scale for scale, _ in steps] == [None]
    for got, want, group in zip(steps[0][1], expected, trainer.optimizer.param_groups):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-9, msg=group["name"])


def spy_on_adam(trainer, params) -> list:
    """Each optimizer step's (gradient_scale or None, the gradients times it: what Adam steps)."""
    steps, real = [], trainer.optimizer.step

    def step(*args, **kwargs):
        scale = kwargs.get("gradient_scale")
        steps.append((scale, [p.grad * (1.0 if scale is None else scale) for p in params]))
        return real(*args, **kwargs)

    trainer.optimizer.step = step
    return steps


@pytest.mark.parametrize("batch", [3, 4])
def test_schedules_count_views_not_steps(small_scene, tmp_path, batch):
    one = Trainer(small_config(small_scene, tmp_path / "one", log_every=2), dict(SCHEDULE))
    one.run()
    many = Trainer(small_config(small_scene, tmp_path / "many", log_every=2, batch_size=batch), dict(SCHEDULE))
    many.run()
    steps = [e["step"] for e in one.history["strategy"]]
    assert steps == [4, 8]
    assert [e["step"] for e in many.history["strategy"]] == steps, "refinements at the same views seen"
    assert {k for e in many.history["strategy"] for k in e} == {k for e in one.history["strategy"] for k in e}
    assert many.step == 12 and many.model.sh_degree == one.model.sh_degree == 3
    # The log points: every multiple of log_every that a step reaches, recorded at the step's end.
    assert many.history["step"] == sorted({math.ceil(i / batch) * batch for i in range(2, 13, 2)})


def test_the_batch_rule_scales_rates_eps_and_betas():
    assert batch_rule(TrainConfig(batch_size=4)) == (2.0, 0.5, 4.0)
    assert batch_rule(TrainConfig(batch_size=4, batch_lr_scale=1.0, batch_beta_power=1.0)) == (1.0, 0.5, 1.0)
    model, _ = hand_model()
    lrs = LearningRates(opacity_logits=0.025)
    optimizer = ops.make_optimizer(model, lrs, 2.0, batch_rule=batch_rule(TrainConfig(batch_size=4)))
    groups = {g["name"]: g for g in optimizer.param_groups}
    assert groups["means"]["lr"] == pytest.approx(lrs.means_init * 2.0 * 2.0)
    assert groups["opacity_logits"]["lr"] == pytest.approx(0.05)
    assert groups["quats"]["eps"] == pytest.approx(0.5e-15)
    assert groups["sh_dc"]["betas"] == pytest.approx((0.9**4, 0.999**4))


def test_resuming_takes_the_commands_rates(small_scene, tmp_path):
    first = Trainer(small_config(small_scene, tmp_path, iters=12), dict(SCHEDULE))
    first.run()
    # The same run continued to 16 views with a batch of 4 and another rotation rate.
    lrs = LearningRates(quats=5e-3)
    again = Trainer(small_config(small_scene, tmp_path, iters=16, resume=True, batch_size=4, lr=lrs), dict(SCHEDULE))
    again._setup()
    groups = {g["name"]: g for g in again.optimizer.param_groups}
    assert groups["quats"]["lr"] == pytest.approx(5e-3 * 2.0)
    assert groups["quats"]["betas"] == pytest.approx((0.9**4, 0.999**4))


def test_step_seeds_and_positions():
    seeds = {step_seed(seed, step) for seed in range(4) for step in range(1, 2000)}
    assert len(seeds) == 4 * 1999, "distinct (seed, step) pairs give distinct seeds"
    assert all(0 <= s < 2**63 for s in seeds)
    assert step_seed(3, 10) == step_seed(3, 10)
    assert my_positions(5, 0, 2) == [0, 2, 4] and my_positions(5, 1, 2) == [1, 3] and my_positions(1, 1, 2) == []
    assert [crossed(b, b + 3, 4) for b in (0, 1, 3, 4)] == [False, True, True, False]
    assert not crossed(0, 100, 0)


def test_the_backend_is_nccl_only_where_every_process_has_a_gpu_of_its_own():
    cuda0, cuda, cpu = torch.device("cuda:0"), torch.device("cuda"), torch.device("cpu")
    assert choose_backend("auto", cuda, 2, 2, spread=True, nccl=True) == "nccl"
    assert choose_backend("auto", cuda0, 2, 2, spread=False, nccl=True) == "gloo", "--device cuda:0 for both"
    assert choose_backend("auto", cuda, 4, 2, spread=True, nccl=True) == "gloo", "more processes than GPUs"
    assert choose_backend("auto", cuda, 2, 2, spread=True, nccl=False) == "gloo"
    assert choose_backend("auto", cpu, 2, 2, spread=True, nccl=True) == "gloo"
    assert choose_backend("auto", cuda0, 1, 1, spread=False, nccl=True) == "nccl", "one process per machine"
    assert choose_backend("gloo", cuda, 2, 2, spread=True, nccl=True) == "gloo"
    with pytest.raises(
        OptionError, match=r"nccl needs a GPU per process: 2 processes .* 2 GPU\(s\), device cuda:0 for all"
    ):
        choose_backend("nccl", cuda0, 2, 2, spread=False, nccl=True)


def test_the_ranks_checksum_sees_any_flipped_bit_and_any_swap():
    """The parameters' checksum (summed on their device, read once) is equal for equal tensors
    and differs when one bit of one element flips, wherever it is, or when two elements swap."""
    from cdcgs.train.distributed import _checksum

    g = torch.Generator().manual_seed(0)
    params = {
        name: torch.randn(*shape, generator=g) for name, shape in (("means", (300, 3)), ("sh_rest", (300, 15, 3)))
    }
    base = _checksum(params)
    assert _checksum({k: v.clone() for k, v in params.items()}) == base
    if torch.cuda.is_available():  # the GPU machine: the same integer sums on the device
        assert _checksum({k: v.cuda() for k, v in params.items()}) == base
    for name, tensor in params.items():
        for position in (0, 1, tensor.numel() // 2, tensor.numel() - 1):
            for bit in (0, 1, 22, 30, 31):
                other = {k: v.clone() for k, v in params.items()}
                other[name].reshape(-1).view(torch.int32)[position] ^= -(1 << 31) if bit == 31 else 1 << bit
                assert _checksum(other) != base, (name, position, bit)
    swapped = {k: v.clone() for k, v in params.items()}
    swapped["means"].reshape(-1)[:2] = params["means"].reshape(-1)[:2].flip(0)
    assert _checksum(swapped) != base


def test_a_failed_process_says_why_before_leaving_the_group(tmp_path, monkeypatch, caplog):
    """On several processes a failure is logged before the process group closes (which can wait
    on a peer stuck inside an exchange, so that nothing else would tell): a defect with its
    traceback, a known failure in one line, bad input not at all (the command line says it)."""
    from cdcgs.train.distributed import RankFailed

    class TwoRanks:  # a caller's own group of two, as far as run() looks at it
        distributed, world, rank, is_main, backend = True, 2, 0, True, "gloo"

    trainer = Trainer(task_config("s", tmp_path / "out"), ranks=TwoRanks())
    said = {}
    for error in (KeyError("boom"), RankFailed("rank 1 died"), OptionError("--iters must be positive")):

        def fail(error=error):
            raise error

        monkeypatch.setattr(trainer, "_run_main", fail)
        caplog.clear()
        with caplog.at_level("ERROR", logger="cdcgs"), pytest.raises(type(error)):
            trainer.run()
        said[type(error).__name__] = caplog.text
    assert "rank 0 failed: Traceback" in said["KeyError"] and "boom" in said["KeyError"]
    assert "rank 0 failed: RankFailed: rank 1 died" in said["RankFailed"] and "Traceback" not in said["RankFailed"]
    assert said["OptionError"] == ""
