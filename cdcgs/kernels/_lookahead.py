"""The device side of a training that renders without reading its counts (``--sync-free``)."""

import warp as wp

from .projection import Camera

__all__ = ["note_render_kernel", "select_camera_at_kernel"]


@wp.kernel(enable_backward=False)
def note_render_kernel(
    pending: wp.array(dtype=wp.int32),
    step_arg: int,
    view_arg: int,
    where: wp.array(dtype=wp.int32),
    halt: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """One thread, after a render with a capacity. ``pending`` [K + 2]: its K non-finite flags of
    the inputs, whether the pairs overflowed the slots, and their count. Writes the count to
    ``counts[view]``; the first render that overflowed or met NaN while ``halt[0]`` is 0 sets
    ``halt[0] = 1`` and ``first = (step, cause, count)``, cause 1 for an overflow and 2 + k for
    input k non-finite (the first such input). The iteration and the view are ``step_arg`` and
    ``view_arg``, or with a non-empty ``where`` its entries 0 and 1 (a step replayed as a CUDA
    graph, whose host writes them before each replay)."""
    step = step_arg
    view = view_arg
    if where.shape[0] > 0:
        step = where[0]
        view = where[1]
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


@wp.kernel(enable_backward=False)
def select_camera_at_kernel(
    cameras: wp.array(dtype=Camera),
    where: wp.array(dtype=wp.int32),
    entry: int,
    camera_out: wp.array(dtype=Camera),
):
    """One thread: ``camera_out[0] = cameras[where[entry]]``: the camera of a view of a step replayed
    as a CUDA graph (its host writes ``where`` before the replay): entry 1 the view it renders; on
    several processes, the step's other views (``--dist-exchange colours`` rebuilds their SH
    gradients)."""
    camera_out[0] = cameras[where[entry]]
