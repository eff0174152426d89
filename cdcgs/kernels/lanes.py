"""Collectives over the 32 lanes of a CUDA warp, and their one-lane meaning on the CPU.

The blend adjoint and the complexity pass accumulate per-Gaussian values from every pixel of a
tile. When the 32 threads of a warp visit the same Gaussian in lockstep, summing their values with
register shuffles first and letting one lane do the atomic turns 32 contended atomics into one.

On CUDA these are warp intrinsics and must be reached by all 32 lanes of the warp together (no
lane may have returned or be inside a branch the others skip). On the CPU every thread is its own
warp: a sum is the value itself, every lane leads. A kernel written with them therefore computes the
same thing on both devices.
"""

import warp as wp

FULL_MASK = "0xffffffffu"


def _butterfly(ctype: str, combine: str) -> str:
    """Native body reducing ``value`` over the warp: ``combine`` of v and the lane ``offset`` away."""
    shuffled = f"__shfl_xor_sync({FULL_MASK}, v, offset)"
    return f"""
#if defined(__CUDA_ARCH__)
    {ctype} v = value;
    for (int offset = 16; offset > 0; offset >>= 1) v = {combine.format(a="v", b=shuffled)};
    return v;
#else
    return value;
#endif
"""


@wp.func_native(_butterfly("float", "{a} + {b}"))
def lane_sum(value: float) -> float: ...


@wp.func_native(_butterfly("float", "fmaxf({a}, {b})"))
def lane_max(value: float) -> float: ...


@wp.func_native(_butterfly("int", "max({a}, {b})"))
def lane_max_int(value: int) -> int: ...


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    return __any_sync({FULL_MASK}, flag);
#else
    return flag;
#endif
"""
)
def lane_any(flag: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return (threadIdx.x & 31) == 0;
#else
    return 1;
#endif
"""
)
def lane_leads() -> int: ...


@wp.func
def lane_sum_vec2(v: wp.vec2):
    return wp.vec2(lane_sum(v[0]), lane_sum(v[1]))


@wp.func
def lane_sum_vec3(v: wp.vec3):
    return wp.vec3(lane_sum(v[0]), lane_sum(v[1]), lane_sum(v[2]))
