"""Input checks as kernels: one launch instead of a chain of torch reductions per render."""

import warp as wp


@wp.func
def flag_nonfinite(values: wp.array(dtype=float), i: int, slot: int, flags: wp.array(dtype=wp.int32)):
    if i < values.shape[0]:
        if not wp.isfinite(values[i]):
            flags[slot] = 1  # every writer writes 1: no atomics needed


@wp.kernel(enable_backward=False)
def find_nonfinite_kernel(
    values0: wp.array(dtype=float),
    values1: wp.array(dtype=float),
    values2: wp.array(dtype=float),
    values3: wp.array(dtype=float),
    values4: wp.array(dtype=float),
    values5: wp.array(dtype=float),
    flags_out: wp.array(dtype=wp.int32),
):
    """``flags_out[k] = 1`` where ``values<k>`` (flat) holds a NaN or an infinity; launch with the
    longest length as dim and ``flags_out`` zeroed. Consecutive threads read consecutive values."""
    i = wp.tid()
    flag_nonfinite(values0, i, 0, flags_out)
    flag_nonfinite(values1, i, 1, flags_out)
    flag_nonfinite(values2, i, 2, flags_out)
    flag_nonfinite(values3, i, 3, flags_out)
    flag_nonfinite(values4, i, 4, flags_out)
    flag_nonfinite(values5, i, 5, flags_out)
