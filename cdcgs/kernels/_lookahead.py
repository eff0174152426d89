"""The device side of a training that renders without reading its counts (``--sync-free``)."""

import warp as wp

__all__ = ["note_render_kernel"]


@wp.kernel(enable_backward=False)
def note_render_kernel(
    pending: wp.array(dtype=wp.int32),
    step: int,
    view: int,
    halt: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """One thread, after a render with a capacity. ``pending`` [K + 2]: its K non-finite flags of
    the inputs, whether the pairs overflowed the slots, and their count. Writes the count to
    ``counts[view]``; the first render that overflowed or met NaN while ``halt[0]`` is 0 sets
    ``halt[0] = 1`` and ``first = (step, cause, count)``, cause 1 for an overflow and 2 + k for
    input k non-finite (the first such input)."""
    k = pending.shape[0] - 2
    count = pending[k + 1]
    counts[view] = count
    cause = int(0)
    for j in range(k):
        if cause == 0 and pending[j] != 0:
            cause = 2 + j
    if cause == 0 and pending[k] != 0:
        cause = 1
    if cause != 0 and halt[0] == 0:
        halt[0] = 1
        first[0] = step
        first[1] = cause
        first[2] = count
