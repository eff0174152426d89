"""The warp collectives of cdcgs.kernels._lanes against numpy: on CUDA over each warp's 32 lanes
(sm_80 and later take ``__reduce_max_sync`` for the maxima, with floats mapped to ordered ints),
on the CPU each thread alone."""

import numpy as np
import torch
import warp as wp

from cdcgs.kernels import BLOCK_SIZE
from cdcgs.kernels._lanes import WARP_SIZE, lane_any, lane_max, lane_max_int, lane_sum


@wp.kernel(enable_backward=False)
def collectives_kernel(
    floats: wp.array(dtype=float),
    ints: wp.array(dtype=wp.int32),
    max_out: wp.array(dtype=float),
    max_int_out: wp.array(dtype=wp.int32),
    sum_out: wp.array(dtype=float),
    any_out: wp.array(dtype=wp.int32),
):
    tid = wp.tid()
    max_out[tid] = lane_max(floats[tid])
    max_int_out[tid] = lane_max_int(ints[tid])
    sum_out[tid] = lane_sum(floats[tid])
    any_out[tid] = lane_any(wp.where(ints[tid] > 900, 1, 0))


def _values(blocks: int):
    """Floats of every sign and scale, with -0.0, +0.0, infinities and subnormals; and ints."""
    rng = np.random.default_rng(0)
    n = blocks * BLOCK_SIZE
    floats = (rng.standard_normal(n) * 10.0 ** rng.integers(-30, 30, n)).astype(np.float32)
    floats[:WARP_SIZE] = -np.abs(floats[:WARP_SIZE])  # a warp of negatives only
    floats[WARP_SIZE : 2 * WARP_SIZE] = 0.0  # a warp of zeros, one of them -0.0
    floats[WARP_SIZE + 5] = -0.0
    special = np.array([np.inf, -np.inf, 1e-45, -1e-45, -0.0], dtype=np.float32)
    floats[2 * WARP_SIZE + 3 : 2 * WARP_SIZE + 3 + len(special)] = special
    floats[3 * WARP_SIZE : 4 * WARP_SIZE] = -np.inf  # a warp of -inf
    ints = rng.integers(-(2**31), 2**31 - 1, n, dtype=np.int64).astype(np.int32)
    ints[4 * WARP_SIZE : 6 * WARP_SIZE] = rng.integers(-1000, 900, 2 * WARP_SIZE)  # no flag in this warp
    ints[5 * WARP_SIZE + 7] = 901  # and one flag in the next
    return floats, ints


def test_the_warp_collectives_are_numpys(device):
    blocks = 3
    floats, ints = _values(blocks)
    n = len(floats)
    tensors = [torch.from_numpy(floats).to(device), torch.from_numpy(ints).to(device)]
    outs = [torch.zeros(n, device=device), torch.zeros(n, dtype=torch.int32, device=device)]
    outs += [torch.zeros(n, device=device), torch.zeros(n, dtype=torch.int32, device=device)]
    dtypes = (wp.float32, wp.int32, wp.float32, wp.int32, wp.float32, wp.int32)
    args = [wp.from_torch(t, dtype=d) for t, d in zip(tensors + outs, dtypes)]
    wp.launch(collectives_kernel, n, inputs=args[:2], outputs=args[2:], device=device, block_dim=BLOCK_SIZE)
    max_out, max_int_out, sum_out, any_out = (t.cpu().numpy() for t in outs)
    lanes = WARP_SIZE if device == "cuda" else 1
    groups = n // lanes
    expected_max = np.repeat(floats.reshape(groups, lanes).max(axis=1), lanes)
    expected_max_int = np.repeat(ints.reshape(groups, lanes).max(axis=1), lanes)
    expected_any = np.repeat((ints.reshape(groups, lanes) > 900).any(axis=1).astype(np.int32), lanes)
    # a max is one of the values, exactly (a -0.0 and a +0.0 may be told apart or not)
    np.testing.assert_array_equal(max_out, expected_max)
    np.testing.assert_array_equal(max_int_out, expected_max_int)
    np.testing.assert_array_equal(any_out != 0, expected_any != 0)
    if lanes == WARP_SIZE:  # a warp without a flag and one with a single flag were taken
        assert expected_any[4 * WARP_SIZE] == 0 and expected_any[5 * WARP_SIZE] == 1
    # the sums in float64, to the float32 butterfly's rounding; warps holding infinities compare as such
    finite = np.isfinite(floats.reshape(groups, lanes)).all(axis=1)
    sums = np.repeat(floats.reshape(groups, lanes).astype(np.float64).sum(axis=1), lanes)
    scale = np.repeat(np.abs(floats.reshape(groups, lanes)).astype(np.float64).sum(axis=1), lanes)
    keep = np.repeat(finite, lanes) & np.isfinite(scale)
    assert keep.sum() >= n // 2
    assert np.all(np.abs(sum_out[keep] - sums[keep]) <= 1e-6 * scale[keep] + 1e-30)
