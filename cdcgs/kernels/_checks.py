"""Input checks as kernels: one launch instead of a chain of torch reductions per render."""

import warp as wp

__all__ = ["find_nonfinite_kernel"]


@wp.func
def flag_nonfinite(values: wp.array(dtype=float), first: int, stride: int, slot: int, flags: wp.array(dtype=wp.int32)):
    found = int(0)
    for k in range(first, values.shape[0], stride):
        if not wp.isfinite(values[k]):
            found = 1
    if found != 0:
        flags[slot] = 1  # every writer writes 1: no atomics needed


@wp.kernel(enable_backward=False)
def find_nonfinite_kernel(
    values0: wp.array(dtype=float),
    values1: wp.array(dtype=float),
    values2: wp.array(dtype=float),
    values3: wp.array(dtype=float),
    values4: wp.array(dtype=float),
    values5: wp.array(dtype=float),
    threads: int,
    flags_out: wp.array(dtype=wp.int32),
):
    """``flags_out[k] = 1`` where ``values<k>`` (flat) holds a NaN or an infinity (``flags_out``
    zeroed before). Launch with ``dim=threads``, any size: thread i reads values i, i + threads,
    i + 2 threads, ... of each input, so consecutive threads read consecutive values."""
    i = wp.tid()
    flag_nonfinite(values0, i, threads, 0, flags_out)
    flag_nonfinite(values1, i, threads, 1, flags_out)
    flag_nonfinite(values2, i, threads, 2, flags_out)
    flag_nonfinite(values3, i, threads, 3, flags_out)
    flag_nonfinite(values4, i, threads, 4, flags_out)
    flag_nonfinite(values5, i, threads, 5, flags_out)
