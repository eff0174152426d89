"""Training on several processes with torch.distributed: the ranks of a run and what they agree on.

A run started by ``torchrun --nproc_per_node=N -m cdcgs train ...`` (or any launcher that sets
torch.distributed's environment: ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``,
``MASTER_PORT``) is data parallel: every rank holds all the Gaussians and the same optimizer,
renders its share of each step's batch of views (positions ``rank``, ``rank + world``, ...), and
adds its gradients and densification statistics to the others' with one flat all-reduce per step.
Adam then runs identically everywhere, and every random draw of a step comes from a generator
seeded by (seed, step) (:func:`step_seed`), so the densification surgery is the same on every
rank. Every ``--check-ranks-every`` steps a checksum of the parameters is compared across ranks;
a difference stops the run (:class:`RankDrift`).

NCCL on CUDA when each rank has a GPU of its own, gloo otherwise (the CPU, or several ranks on one
GPU); the process group's timeout bounds every collective, so a rank that dies or hangs ends the
run on the others (:class:`RankFailed`) instead of hanging it. Only rank 0 writes into the run
folder. docs/distributed.md has the rules and the measurements.
"""

from __future__ import annotations

import contextlib
import datetime
import os

import torch

from ..errors import OptionError

__all__ = [
    "RankDrift",
    "RankFailed",
    "Ranks",
    "StatisticsSync",
    "balanced_positions",
    "choose_backend",
    "my_positions",
    "rank_device",
    "step_seed",
]

BACKENDS = ("auto", "nccl", "gloo")
_MASK64 = (1 << 64) - 1


class RankFailed(RuntimeError):
    """Another rank failed, died or stopped answering; this one stops too."""


class RankDrift(RuntimeError):
    """The ranks' parameters differ: the data-parallel invariant broke (a bug, or hardware)."""


def step_seed(seed: int, step: int) -> int:
    """The seed of the generator of the step that begins at iteration ``step`` of a run seeded
    ``seed``: splitmix64 of the pair, so that neighbouring seeds and steps give unrelated streams,
    every rank and a resumed run draw the same numbers, and no state needs carrying over."""
    z = ((seed & 0xFFFFFFFF) << 32 | (step & 0xFFFFFFFF)) & _MASK64
    z = (z + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return (z ^ (z >> 31)) & ((1 << 63) - 1)


def my_positions(batch: int, rank: int, world: int) -> list[int]:
    """The positions in a step's batch of ``batch`` views that ``rank`` of ``world`` renders:
    ``rank``, ``rank + world``, ... (none when the batch is smaller than the rank)."""
    return list(range(rank, batch, world))


def splits_by_counts(count: int, world: int) -> bool:
    """Whether ``--dist-balance counts`` can split a batch of ``count`` views over ``world``
    processes: a multiple of them, two views or more each."""
    return count % world == 0 and count >= 2 * world


def balanced_positions(costs: list, rank: int, world: int, turn: int = 0) -> list[int]:
    """The positions of a step's batch that ``rank`` of ``world`` renders when the view at position
    ``p`` costs ``costs[p]`` (e.g. its intersection count): every process takes ``len(costs) /
    world`` of them (the batch a multiple of ``world``), the costliest first, each to the process
    with the least cost so far, so that the processes reach the all-reduce together. Two views a
    process pairs the costliest with the cheapest. Ties go to the earlier position, and among
    processes of equal cost to the first from rank ``turn % world`` on (the step's number: the
    costliest view goes to each process in turn, so rank 0's logged losses are of no one kind of
    view). Every process computes the same split from the same costs. Returned in batch order."""
    batch = len(costs)
    if world < 1 or batch % world:
        raise ValueError(f"a batch of {batch} views does not split evenly over {world} processes")
    share = batch // world
    loads, taken = [0.0] * world, [[] for _ in range(world)]
    for position in sorted(range(batch), key=lambda p: (-costs[p], p)):
        owner = min((r for r in range(world) if len(taken[r]) < share), key=lambda r: (loads[r], (r - turn) % world))
        taken[owner].append(position)
        loads[owner] += costs[position]
    return sorted(taken[rank])


def _environment() -> tuple[int, int, int, int]:
    """(rank, world, local rank, local world) from torch.distributed's variables; (0, 1, 0, 1)
    without them."""

    def read(name: str, default: int) -> int:
        value = os.environ.get(name)
        if value is None or value == "":
            return default
        try:
            return int(value)
        except ValueError:
            raise OptionError(f"environment variable {name}={value!r} is not an integer") from None

    world = read("WORLD_SIZE", 1)
    rank = read("RANK", 0)
    local_rank = read("LOCAL_RANK", rank)
    local_world = read("LOCAL_WORLD_SIZE", world)
    if world < 1 or not 0 <= rank < world or not 0 <= local_rank < max(local_world, 1):
        raise OptionError(
            f"torch.distributed's environment is inconsistent: RANK={rank}, WORLD_SIZE={world}, "
            f"LOCAL_RANK={local_rank}, LOCAL_WORLD_SIZE={local_world}"
        )
    return rank, world, local_rank, local_world


def rank_device(option: str, local_rank: int, local_world: int) -> str:
    """The device of the rank ``local_rank`` of ``local_world`` on its machine for a ``--device``
    option: ``auto`` and ``cuda`` spread the ranks over the GPUs (rank i on GPU i mod count),
    ``cuda:K`` and ``cpu`` put every rank there."""
    if option in ("auto", "cuda") and torch.cuda.is_available():
        return f"cuda:{local_rank % torch.cuda.device_count()}"
    return option


def choose_backend(option: str, device: torch.device, local_world: int, gpus: int, spread: bool, nccl: bool) -> str:
    """The backend for ``--dist-backend option``: ``auto`` is NCCL when every one of the
    ``local_world`` processes of this machine has a GPU of its own (CUDA ``device``, enough of the
    machine's ``gpus``, and the devices ``spread`` over them, not one named for all) and NCCL is
    ``nccl``-available, gloo otherwise; ``nccl`` where that does not hold is refused."""
    own_gpus = device.type == "cuda" and local_world <= gpus and (spread or local_world == 1)
    if option == "auto":
        return "nccl" if own_gpus and nccl else "gloo"
    if option == "nccl" and not own_gpus:
        raise OptionError(
            f"--dist-backend nccl needs a GPU per process: {local_world} processes on this machine, {gpus} GPU(s), "
            f"device {device}{'' if spread else ' for all of them'} (use gloo to share a GPU or to train on the CPU)"
        )
    return option


class Ranks:
    """The processes of a run: ``rank`` of ``world``, and the collectives the trainer uses. One
    process (``Ranks.single()``) is the world of one, where every collective is the identity."""

    def __init__(self, rank: int = 0, world: int = 1, backend: str | None = None, owns_group: bool = False):
        self.rank, self.world, self.backend = rank, world, backend
        self._owns_group = owns_group

    @classmethod
    def single(cls) -> Ranks:
        return cls()

    @classmethod
    def from_environment(
        cls, device: torch.device, backend: str = "auto", timeout: float = 600.0, spread: bool = True
    ) -> Ranks:
        """The ranks of a launch by torchrun (or anything that sets its variables); one process
        when ``WORLD_SIZE`` is unset or 1. Joins the default process group (or uses the one the
        caller initialised), with ``backend`` (``auto``: NCCL on CUDA when every rank of this
        machine has a GPU of its own, gloo otherwise) and ``timeout`` seconds on every collective.
        ``spread``: the ranks' devices came from :func:`rank_device` of ``auto`` or ``cuda`` (one
        GPU each where there are enough); False when the command named one device for all (the
        decision must be the same on every rank, so it rests on the option, not on ``device``)."""
        if backend not in BACKENDS:
            raise OptionError(f"--dist-backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            return cls(dist.get_rank(), dist.get_world_size(), dist.get_backend(), owns_group=False)
        rank, world, _, local_world = _environment()
        if world == 1:
            return cls.single()
        if not dist.is_available():
            raise OptionError("this torch build has no torch.distributed: it cannot train on several processes")
        gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
        backend = choose_backend(backend, device, local_world, gpus, spread, dist.is_nccl_available())
        for name in ("MASTER_ADDR", "MASTER_PORT"):
            if not os.environ.get(name):
                raise OptionError(f"WORLD_SIZE={world} but {name} is not set: launch with torchrun")
        options = {"backend": backend, "rank": rank, "world_size": world}
        options["timeout"] = datetime.timedelta(seconds=timeout)
        if backend == "nccl":
            options["device_id"] = device
        if device.type == "cuda":  # the collectives' own tensors (all_gather_object's) go to this GPU
            torch.cuda.set_device(device)
        dist.init_process_group(**options)
        return cls(rank, world, backend, owns_group=True)

    # ------------------------------------------------------------------------------- facts

    @property
    def distributed(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def close(self, wait: bool = False) -> None:
        """Leave the process group this object joined (not one the caller made). ``wait``: after
        a barrier, when every process ends normally: gloo's worker thread otherwise may release
        the last collective's tensors while the interpreter exits, which aborts the process."""
        if self._owns_group:
            import torch.distributed as dist

            if dist.is_initialized():
                if wait:
                    with contextlib.suppress(RuntimeError, OSError):  # a peer already gone: nothing to wait for
                        dist.barrier()
                dist.destroy_process_group()
            self._owns_group = False

    # -------------------------------------------------------------------------- collectives

    def _collective(self, what: str, call):
        try:
            return call()
        except (RuntimeError, OSError) as err:  # gloo and NCCL report a dead or late peer so
            if isinstance(err, (RankFailed, RankDrift)):
                raise
            raise RankFailed(
                f"rank {self.rank} of {self.world}: {what} failed, another rank died, stopped or timed out ({err})"
            ) from err

    def all_reduce_(self, tensor: torch.Tensor, op: str = "sum") -> torch.Tensor:
        """Reduce ``tensor`` over the ranks in place (``sum``, ``max`` or ``min``)."""
        if not self.distributed:
            return tensor
        import torch.distributed as dist

        ops = {"sum": dist.ReduceOp.SUM, "max": dist.ReduceOp.MAX, "min": dist.ReduceOp.MIN}
        if tensor.is_cuda and self.backend == "gloo":
            # gloo reduces host memory: reduce a host copy and copy it back on this stream
            host = tensor.cpu()
            self._collective(f"all_reduce ({op})", lambda: dist.all_reduce(host, op=ops[op]))
            tensor.copy_(host)
            return tensor
        self._collective(f"all_reduce ({op})", lambda: dist.all_reduce(tensor, op=ops[op]))
        return tensor

    def all_gather_(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` (the same shape on each), stacked in rank order along a new
        first dimension."""
        if not self.distributed:
            return tensor[None]
        import torch.distributed as dist

        if self.backend == "gloo":  # gloo gathers host memory into a list
            host = tensor.cpu()
            parts = [torch.empty_like(host) for _ in range(self.world)]
            self._collective("all_gather", lambda: dist.all_gather(parts, host))
            return torch.stack(parts).to(tensor.device)
        out = tensor.new_empty((self.world, *tensor.shape))
        self._collective("all_gather", lambda: dist.all_gather_into_tensor(out, tensor.contiguous()))
        return out

    def all_gather_object(self, obj) -> list:
        """Every rank's ``obj`` (picklable), in rank order."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world
        self._collective("all_gather_object", lambda: dist.all_gather_object(out, obj))
        return out

    def gather_object(self, obj) -> list | None:
        """Every rank's ``obj`` on rank 0 (in rank order); None on the others."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world if self.is_main else None
        self._collective("gather_object", lambda: dist.gather_object(obj, out, dst=0))
        return out

    def all_ok(self, error: BaseException | None, when: str) -> None:
        """Agree that every rank got through ``when``: re-raise ``error`` on the rank that has it,
        and raise :class:`RankFailed`, naming the failed ranks and their errors, on the others."""
        if not self.distributed:
            if error is not None:
                raise error
            return
        reports = self.all_gather_object(None if error is None else f"{type(error).__name__}: {error}")
        if error is not None:
            raise error
        failed = [(rank, report) for rank, report in enumerate(reports) if report is not None]
        if failed:
            described = "; ".join(f"rank {rank}: {report}" for rank, report in failed)
            raise RankFailed(f"{when} failed on {len(failed)} of {self.world} ranks ({described})")

    def reduce_gradients(
        self, params, count: int, extras: list[torch.Tensor] = (), divide: bool = True
    ) -> list[torch.Tensor]:
        """Sum the gradients of ``params`` over the ranks in one flat all-reduce and divide them by
        ``count``, the views of the whole batch (a parameter this rank gave no gradient counts as
        zeros); ``extras`` (float tensors) travel in the same buffer, summed, and come back in
        order. One process: the division only. ``divide=False``: the sums, for an optimizer that
        takes the division itself (``FusedAdam``'s ``gradient_scale``)."""
        params = list(params)
        if not self.distributed:
            if count != 1 and divide:
                for p in params:
                    if p.grad is not None:
                        p.grad.div_(count)
            return list(extras)
        device = params[0].device
        pieces = [p.grad.reshape(-1) if p.grad is not None else torch.zeros(p.numel(), device=device) for p in params]
        pieces += [e.reshape(-1).to(device=device, dtype=torch.float32) for e in extras]
        flat = torch.cat(pieces)
        self.all_reduce_(flat)
        flat_grads = flat[: sum(p.numel() for p in params)]
        if divide and count != 1:
            flat_grads.div_(count)
        offset = 0
        for p in params:  # views of the buffer: no copy back (the optimizer reads them in place)
            p.grad = flat_grads[offset : offset + p.numel()].view_as(p)
            offset += p.numel()
        out = []
        for e in extras:
            out.append(flat[offset : offset + e.numel()].view_as(e).to(e.dtype))
            offset += e.numel()
        return out

    def check_in_step(self, params: dict, step: int) -> None:
        """Compare a checksum of ``params`` across the ranks; :class:`RankDrift` when they differ."""
        if not self.distributed:
            return
        mine = _checksum(params)
        sums = self.all_gather_object(mine)
        if any(s != sums[0] for s in sums):
            raise RankDrift(
                f"at iteration {step} the ranks' parameters differ (checksums {sums}): the data-parallel "
                "run is no longer one run; its last checkpoint is the last good state"
            )


# Two primes below 2^31: a parameter's bits differing anywhere change at least one of its sums.
CHECKSUM_PRIMES = (2_147_483_647, 2_147_483_629)
CHECKSUM_CHUNK = 1 << 24  # elements per pass, bounding the sums' temporaries


def _checksum(params: dict) -> str:
    """Equal on every process exactly when the ranks hold the same ``params``, as far as a check
    can tell: per tensor, sum over its elements of bits * (position mod 65521 + 1), modulo each of
    CHECKSUM_PRIMES, in integers on the tensors' own device (no copy of the parameters to the host).

    One element whose 32 bits differ always changes a sum: the difference d (0 < |d| < 2^32) times
    a weight below both primes would have to be a multiple of their product (about 2^62). Several
    differences cancel only by chance (about 1 in 2^62)."""
    sums = []
    for name in sorted(params):
        flat = params[name].detach().reshape(-1)
        if flat.element_size() != 4:
            flat = flat.float()
        bits = flat.view(torch.int32)
        totals = [torch.zeros((), dtype=torch.int64, device=flat.device) for _ in CHECKSUM_PRIMES]
        for start in range(0, bits.numel(), CHECKSUM_CHUNK):
            chunk = bits[start : start + CHECKSUM_CHUNK].long() & 0xFFFFFFFF
            weights = torch.arange(start, start + chunk.numel(), device=flat.device) % 65521 + 1
            terms = chunk * weights  # below 2^48
            for total, prime in zip(totals, CHECKSUM_PRIMES):
                total += (terms % prime).sum() % prime  # a chunk's sum stays below 2^55
        sums += totals
    values = torch.stack(sums).tolist() if sums else []  # the one read from the device
    return "-".join(f"{v % CHECKSUM_PRIMES[i % 2]:x}" for i, v in enumerate(values))


class StatisticsSync:
    """Sums a strategy's densification statistics over the ranks once per step.

    ``kinds`` maps state keys to ``sum`` (gradient sums, view counts: the ranks' additions of the
    step are reduced, not their totals, so nothing is counted twice) or ``max`` (screen radii,
    the max of Γ: reduced as they are). :meth:`begin` notes the sums at the start of a step,
    :meth:`deltas` gives what this rank added since (to travel with the gradients), and
    :meth:`finish` writes back start + the reduced additions and reduces the maxima, in place (a
    step replayed as a CUDA graph reads and writes the same tensors every time). With a ``halt``
    (``--sync-free``: some process's render overflowed) every statistic keeps its value from the
    start of the step, which is taken again."""

    def __init__(self, ranks: Ranks, kinds: dict[str, str]):
        bad = {k: v for k, v in kinds.items() if v not in ("sum", "max")}
        if bad:
            raise ValueError(f"statistics must be reduced by sum or max, got {bad}")
        self.ranks, self.kinds = ranks, dict(kinds)
        self._start: dict[str, torch.Tensor] = {}
        self._held: dict[str, torch.Tensor] = {}

    def _keys(self, state: dict, kind: str) -> list[str]:
        return [k for k, v in self.kinds.items() if v == kind and k in state]

    def begin(self, state: dict, halts: bool = False) -> None:
        """Note the sums (and with ``halts``, the maxima too) at the start of a step."""
        self._start = {k: state[k].clone() for k in self._keys(state, "sum")}
        self._held = {k: state[k].clone() for k in self._keys(state, "max")} if halts else {}

    def deltas(self, state: dict) -> list[torch.Tensor]:
        return [(state[k] - self._start[k]).float() for k in self._start]

    def finish(self, state: dict, reduced: list[torch.Tensor], halt: torch.Tensor | None = None) -> None:
        held = None if halt is None else halt.bool()
        for k, delta in zip(list(self._start), reduced):
            total = self._start[k] + delta.to(state[k].dtype)
            state[k].copy_(total if held is None else torch.where(held, self._start[k], total))
        for k in self._keys(state, "max"):
            self.ranks.all_reduce_(state[k], "max")
            if held is not None:
                state[k].copy_(torch.where(held, self._held[k], state[k]))
        self._start, self._held = {}, {}
