"""Sharing torch tensors with Warp: zero-copy arrays, the right device and stream."""

import contextlib
import threading

import torch
import warp as wp

# Idempotent; needed before wp.device_from_torch, which reads Warp's device list.
wp.init()

_TORCH_DTYPES = {wp.int32: torch.int32, wp.int64: torch.int64, wp.float32: torch.float32}
_VECTOR_TYPES = {wp.vec3: (torch.float32, 3), wp.vec2: (torch.float32, 2), wp.vec2i: (torch.int32, 2), wp.vec4i: (torch.int32, 4)}


def wp_array(tensor: torch.Tensor, dtype) -> wp.array:
    """A Warp view of a contiguous tensor's memory (no copy)."""
    return wp.from_torch(tensor, dtype=dtype, requires_grad=False)


_descriptors: dict = {}


def wp_arg(tensor: torch.Tensor, dtype):
    """A kernel argument viewing ``tensor``'s memory: Warp's low-level array descriptor, cached by
    address, shape, strides and type (torch's allocator hands the same blocks back every iteration,
    and a render passes ~70 arrays: building each anew cost more host time than some kernels).

    Only for ``wp.launch`` arguments, used while ``tensor`` is alive; the descriptor holds no
    reference to it. Use :func:`wp_array` for a Warp array to keep or to slice.
    """
    key = (tensor.data_ptr(), tensor.shape, tensor.stride(), tensor.dtype, tensor.device, dtype)
    descriptor = _descriptors.get(key)
    if descriptor is None:
        if len(_descriptors) >= 1024:
            _descriptors.clear()
        descriptor = wp.from_torch(tensor, dtype=dtype, requires_grad=False, return_ctype=True)
        # from_torch pins the tensor to its descriptor; a cached pin would keep every tensor ever
        # passed alive (and make autograd copy gradients it could otherwise take over).
        descriptor._ref = descriptor._gradref = None
        _descriptors[key] = descriptor
    return descriptor


_streams: dict = {}
# Warp's default device and each device's current stream are process-wide; two threads (a training
# and its viewer) entering and leaving scopes in an interleaved order could leave either launching
# on the other's stream. One scope at a time; re-entrant for nested scopes in one thread.
_scope_lock = threading.RLock()


_active = threading.local()


@contextlib.contextmanager
def warp_scope(device: torch.device):
    """Run Warp on the tensors' device and, on CUDA, on torch's current stream (thread-safe).

    A scope nested in one for the same device in the same thread costs nothing: the outer one's
    device and stream stay (the stream is the one current when the outer scope was entered).
    """
    key = (device.type, device.index)
    outer = getattr(_active, "key", None), getattr(_active, "device", None)
    if outer[0] == key:
        yield outer[1]
        return
    with _scope_lock, _scoped(device) as warp_device:
        _active.key, _active.device = key, warp_device
        try:
            yield warp_device
        finally:
            _active.key, _active.device = outer


@contextlib.contextmanager
def _scoped(device: torch.device):
    if device.type == "cuda":
        torch_stream = torch.cuda.current_stream(device)
        key = (device.index, torch_stream.cuda_stream)
        stream = _streams.get(key)
        if stream is None:
            stream = _streams[key] = wp.stream_from_torch(torch_stream)
        with wp.ScopedDevice(stream.device), wp.ScopedStream(stream, sync_enter=False):
            yield stream.device
    else:
        with wp.ScopedDevice("cpu"):
            yield wp.get_device("cpu")


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
