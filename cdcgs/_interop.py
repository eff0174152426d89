"""Sharing torch tensors with Warp: zero-copy arrays, the right device and stream (private to cdcgs).

Warp's runtime is initialised on first use (:func:`ensure_warp`, called by every function here that
needs it), not when cdcgs is imported. What is kept between launches (launch descriptors, recorded
launches, Warp streams wrapping torch's) belongs to one :class:`TorchWarpBridge`, ``BRIDGE``.
"""

import contextlib
import ctypes
import functools
import threading
import time

import torch
import warp as wp

__all__ = [
    "BRIDGE",
    "TorchWarpBridge",
    "device_clock",
    "ensure_warp",
    "halt_arg",
    "launch",
    "small_table",
    "torch_allocators",
    "torch_tensor",
    "unpin_descriptor",
    "warp_device",
    "warp_scope",
    "wp_arg",
    "wp_array",
]

_TORCH_DTYPES = {wp.int32: torch.int32, wp.int64: torch.int64, wp.float32: torch.float32, wp.uint8: torch.uint8}
_VECTOR_TYPES = {
    wp.vec3: (torch.float32, 3),
    wp.vec2: (torch.float32, 2),
    wp.vec2i: (torch.int32, 2),
    wp.vec4i: (torch.int32, 4),
}


def device_clock(device: torch.device) -> float:
    """time.perf_counter() once ``device``'s queued work is done (a synchronisation on CUDA)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def ensure_warp() -> None:
    """Initialise Warp's runtime if it is not yet (idempotent; a no-op after the first call).

    ``wp.device_from_torch``, under ``wp.from_torch`` and ``wp.stream_from_torch``, reads Warp's
    device list, which exists only once the runtime is initialised.
    """
    wp.init()


def wp_array(tensor: torch.Tensor, dtype) -> wp.array:
    """A Warp view of a contiguous tensor's memory (no copy), which keeps the tensor alive and
    hands it back (:func:`torch_tensor`).

    Built with ``wp.array(ptr=...)``: ``wp.from_torch`` took twice as long (5 us on a 2-core
    CPU), handling strides, gradients and storage offsets that these views do not have.
    """
    base, length = _VECTOR_TYPES.get(dtype, (_TORCH_DTYPES.get(dtype), 0))
    shape = tuple(tensor.shape[:-1]) if length else tuple(tensor.shape)
    if tensor.dtype != base or (length and tensor.shape[-1:] != (length,)) or not tensor.is_contiguous():
        inner = f" [..., {length}]" if length else ""
        raise ValueError(
            f"{dtype.__name__} views a contiguous {base}{inner} tensor, got {tensor.dtype} {list(tensor.shape)}"
        )
    array = wp.array(ptr=tensor.data_ptr(), dtype=dtype, shape=shape, device=_warp_device(tensor.device))
    array._cdcgs_tensor = tensor  # keeps the memory alive as long as the view
    return array


def torch_tensor(array: wp.array) -> torch.Tensor:
    """The tensor of a :func:`wp_array` view; of any other Warp array, ``wp.to_torch``'s view."""
    tensor = getattr(array, "_cdcgs_tensor", None)
    return wp.to_torch(array, requires_grad=False) if tensor is None else tensor


def small_table(device: torch.device, rows: list, dtype: torch.dtype) -> torch.Tensor:
    """A small table of host values on ``device`` (a kernel's argument table); on CUDA copied from
    pinned memory without waiting (torch's pinned allocator keeps the host block until the copy has
    run)."""
    if device.type != "cuda":
        return torch.tensor(rows, dtype=dtype)
    return torch.tensor(rows, dtype=dtype, pin_memory=True).to(device, non_blocking=True)


@functools.cache
def _warp_device(device: torch.device):
    """Warp's device of a torch device (kept: ``wp.device_from_torch`` parses its name)."""
    ensure_warp()
    return wp.device_from_torch(device)


def warp_device(device: torch.device):
    """Warp's device of a torch device; ``cuda`` without an ordinal is torch's current GPU (Warp
    cannot map that name)."""
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return _warp_device(device)


def unpin_descriptor(descriptor) -> None:
    """Let go of the tensor (and gradient) that ``wp.from_torch(..., return_ctype=True)`` pins to
    the descriptor it returns, so that a cached descriptor keeps no tensor alive.

    The one place in cdcgs that touches Warp's private attributes (``_ref`` and ``_gradref``, Warp
    1.19): a cache of pinned descriptors would keep every tensor ever passed allocated (and make
    autograd copy gradients it could otherwise take over). tests/test_warp_api.py checks that Warp
    still sets these attributes and that a tensor is freed once they are cleared; a Warp without
    them raises here instead of leaking silently.
    """
    if not (hasattr(descriptor, "_ref") and hasattr(descriptor, "_gradref")):
        raise RuntimeError(
            f"wp.from_torch(return_ctype=True) of Warp {wp.__version__} no longer sets _ref/_gradref: update cdcgs._interop.unpin_descriptor"
        )
    descriptor._ref = descriptor._gradref = None


class TorchWarpBridge:
    """What cdcgs keeps between Warp launches on torch tensors, and the scope that launches run in.

    - Launch descriptors (:meth:`descriptor`), cached by address, shape, strides and type: torch's
      caching allocator hands the same blocks back every iteration, and a render passes ~70 arrays
      (building each anew cost more host time than some kernels). At most ``max_descriptors``;
      the cache is emptied when full.
    - Recorded launches (:meth:`launch`), one per kernel, device and launch kind, replayed with
      each call's arguments: ``wp.launch`` checks, converts and packs every argument and resolves
      the kernel's module on every call, the host time of a small kernel.
    - Warp streams wrapping torch's CUDA streams, one per (device index, stream handle).
    - :meth:`scope`: Warp's default device and each device's current stream are process-wide, so
      two threads (a training and its viewer) entering and leaving scopes in an interleaved order
      could leave either launching on the other's stream. One scope at a time; re-entrant for
      nested scopes in one thread.

    cdcgs uses one instance, ``BRIDGE``; what it mirrors (torch's allocator and streams, Warp's
    current device and stream) is process-wide too.
    """

    def __init__(self, max_descriptors: int = 1024):
        self.max_descriptors = max_descriptors
        self._descriptors: dict = {}
        self._launches: dict = {}
        self._streams: dict = {}
        self._lock = threading.RLock()
        self._active = threading.local()

    def descriptor(self, tensor: torch.Tensor, dtype):
        """A kernel argument viewing ``tensor``'s memory: Warp's low-level array descriptor.

        Only for ``wp.launch`` arguments, used while ``tensor`` is alive; the descriptor holds no
        reference to it. Use :func:`wp_array` for a Warp array to keep or to slice.
        """
        key = (tensor.data_ptr(), tensor.shape, tensor.stride(), tensor.dtype, tensor.device, dtype)
        descriptor = self._descriptors.get(key)
        if descriptor is None:
            if len(self._descriptors) >= self.max_descriptors:
                self._descriptors.clear()
            ensure_warp()
            descriptor = wp.from_torch(tensor, dtype=dtype, requires_grad=False, return_ctype=True)
            unpin_descriptor(descriptor)
            self._descriptors[key] = descriptor
        return descriptor

    def launch(
        self,
        kernel,
        dim,
        inputs=(),
        outputs=(),
        adj_inputs=(),
        adj_outputs=(),
        device=None,
        adjoint: bool = False,
        block_dim: int | None = None,
    ) -> None:
        """``wp.launch`` with the same arguments, for a kernel launched again and again.

        The first launch of ``kernel`` on a device (forward or adjoint, at a block size) is
        recorded (``wp.launch(..., record_cmd=True)``); later ones replay that record, setting the
        launch size and the arguments that are not the very objects of the last launch (cached
        descriptors, the same camera, None) without Warp's checks and conversions. Arguments as
        ``wp.launch`` takes them; Warp arrays are held as descriptors, so that no record keeps a
        buffer alive. Records are set and launched under the bridge's lock.
        """
        values = [_descriptor_of(value) for value in (*inputs, *outputs, *adj_inputs, *adj_outputs)]
        with self._lock:
            device = wp.get_device(device)
            key = (kernel, device.alias, adjoint, block_dim, len(inputs) + len(outputs))
            replay = self._launches.get(key)
            if replay is None:
                if kernel.is_generic:  # overloads resolved from the arguments: no one record
                    wp.launch(
                        kernel,
                        dim,
                        inputs,
                        outputs,
                        adj_inputs,
                        adj_outputs,
                        device,
                        adjoint=adjoint,
                        block_dim=block_dim,
                    )
                    return
                count = len(inputs) + len(outputs)
                record = wp.launch(
                    kernel,
                    dim,
                    values[:count],
                    adj_inputs=values[count:],
                    device=device,
                    adjoint=adjoint,
                    block_dim=block_dim,
                    record_cmd=True,
                )
                if record is None:  # an empty launch: nothing to run, nothing recorded
                    return
                replay = self._launches[key] = _Replay(record, dim, values, count)
            else:
                replay.update(dim, values)
            replay.record.launch()

    @contextlib.contextmanager
    def scope(self, device: torch.device):
        """Run Warp on the tensors' device and, on CUDA, on torch's current stream (thread-safe).

        A scope nested in one for the same device and torch stream in the same thread costs only
        the look at torch's current stream: the outer one's device and stream stay. Nested under
        another torch stream (a ``torch.cuda.stream`` entered inside the outer scope), it runs
        Warp on that stream until it ends.
        """
        # A scope under another torch stream than the outer one's is a scope of its own, so that a
        # caller's ``torch.cuda.stream`` reaches the launches of cdcgs functions it calls.
        stream = torch.cuda.current_stream(device).cuda_stream if device.type == "cuda" else None
        key = (device.type, device.index, stream)
        active = self._active
        outer = getattr(active, "key", None), getattr(active, "device", None)
        if outer[0] == key:
            yield outer[1]
            return
        ensure_warp()
        with self._lock, self._scoped(device) as warp_device:
            active.key, active.device = key, warp_device
            try:
                yield warp_device
            finally:
                active.key, active.device = outer

    @contextlib.contextmanager
    def _scoped(self, device: torch.device):
        if device.type == "cuda":
            torch_stream = torch.cuda.current_stream(device)
            key = (device.index, torch_stream.cuda_stream)
            stream = self._streams.get(key)
            if stream is None:
                stream = self._streams[key] = wp.stream_from_torch(torch_stream)
            with wp.ScopedDevice(stream.device), wp.ScopedStream(stream, sync_enter=False):
                yield stream.device
        else:
            with wp.ScopedDevice("cpu"):
                yield wp.get_device("cpu")


def _descriptor_of(value):
    """A Warp array as its descriptor (which holds no reference to its memory); anything else as
    it is."""
    return value.__ctype__() if isinstance(value, wp.array) else value


class _Replay:
    """A recorded launch and the argument objects it was last set to."""

    __slots__ = ("count", "dim", "record", "values")

    def __init__(self, record, dim, values: list, count: int):
        self.record, self.dim, self.values, self.count = record, dim, values, count

    def update(self, dim, values: list) -> None:
        record = self.record
        if dim != self.dim:
            record.set_dim(dim)
            self.dim = dim
        last, count = self.values, self.count
        for i, value in enumerate(values):
            if value is last[i]:
                continue
            adjoint = i >= count
            index = i - count if adjoint else i
            if isinstance(value, (ctypes.Structure, int, float)):  # descriptors, numbers: set as they are
                record.set_param_at_index_from_ctype(index, value, adjoint)
            else:  # None, Warp structs and vectors: packed by Warp
                record.set_param_at_index(index, value, adjoint)
            last[i] = value


BRIDGE = TorchWarpBridge()
# The bridge's methods under the names the torch face uses.
wp_arg = BRIDGE.descriptor
warp_scope = BRIDGE.scope
launch = BRIDGE.launch


def torch_allocators(device: torch.device):
    """(allocate, zeros) callables for Warp helpers that return Warp views of new torch tensors,
    so that torch's caching allocator holds (and reports) every buffer."""

    def allocate(shape, dtype, _device):
        if dtype in _VECTOR_TYPES:
            base, length = _VECTOR_TYPES[dtype]
            return wp_array(torch.empty(*shape, length, dtype=base, device=device), dtype)
        return wp_array(torch.empty(shape, dtype=_TORCH_DTYPES[dtype], device=device), dtype)

    def zeros(shape, dtype, _device):
        return wp_array(torch.zeros(shape, dtype=_TORCH_DTYPES[dtype], device=device), dtype)

    return allocate, zeros


def halt_arg(halt: torch.Tensor | None, device: torch.device):
    """The ``halt`` argument of the kernels that change a training's state (Adam, the densification
    statistics, MCMC's noise): ``halt``, an int32 device tensor whose first entry stops them while
    non-zero, or an empty array (never halted) for None."""
    if halt is None:
        halt = _never_halted(torch.device(device))
    elif halt.dtype != torch.int32 or halt.device != torch.device(device) or halt.numel() < 1:
        raise ValueError(
            f"halt must be an int32 tensor of at least one entry on {device}, got {halt.dtype} {list(halt.shape)} on {halt.device}"
        )
    return wp_arg(halt, wp.int32)


@functools.cache
def _never_halted(device: torch.device) -> torch.Tensor:
    """The empty ``halt`` of a device, made once: every step of a training without --sync-free
    passes it to Adam and the statistics kernel."""
    return torch.empty(0, dtype=torch.int32, device=device)
