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

from ._constants import BLOCK_SIZE

__all__ = [
    "BATCH_FIELDS",
    "BATCH_LOAD",
    "BATCH_MAX",
    "BATCH_STORE",
    "GRADIENTS_ADD",
    "GRADIENTS_READ",
    "GRADIENTS_ZERO",
    "GROUP_SIZE",
    "WARP_SIZE",
    "atomic_max_nonnegative",
    "batch_max",
    "block_count",
    "block_gradients",
    "block_max_int",
    "block_sync",
    "group_read",
    "lane_any",
    "lane_leads",
    "lane_max",
    "lane_max_int",
    "lane_sum",
    "lane_sum_vec2",
    "lane_sum_vec3",
    "on_cuda",
    "tile_batch",
    "tile_ids",
]

# Lanes of a CUDA warp; the native snippets below are generated from it.
WARP_SIZE = 32
FULL_MASK = "0xffffffffu"
# A block must be whole warps: the collectives need every lane of a warp in the block.
assert BLOCK_SIZE % WARP_SIZE == 0, f"BLOCK_SIZE ({BLOCK_SIZE}) must be a multiple of the warp size ({WARP_SIZE})"


def _butterfly(ctype: str, combine: str) -> str:
    """Native body reducing ``value`` over the warp: ``combine`` of v and the lane ``offset`` away."""
    shuffled = f"__shfl_xor_sync({FULL_MASK}, v, offset)"
    return f"""
#if defined(__CUDA_ARCH__)
    {ctype} v = value;
    for (int offset = {WARP_SIZE // 2}; offset > 0; offset >>= 1) v = {combine.format(a="v", b=shuffled)};
    return v;
#else
    return value;
#endif
"""


@wp.func_native(_butterfly("float", "{a} + {b}"))
def lane_sum(value: float) -> float: ...


def _reduced(ctype: str, combine: str, to_int: str, from_int: str) -> str:
    """Native body of a warp max: on sm_80 and later one ``__reduce_max_sync`` (a single warp
    instruction, where the butterfly takes five shuffles and five combines) on ``value`` mapped to
    an int by ``to_int`` and back by ``from_int``; before sm_80 the butterfly of ``combine``."""
    butterfly = _butterfly(ctype, combine).replace("#if defined(__CUDA_ARCH__)", "#elif defined(__CUDA_ARCH__)")
    return f"""
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
    const int reduced = __reduce_max_sync({FULL_MASK}, {to_int.format(v="value")});
    return {from_int.format(v="reduced")};{butterfly}"""


# A float's bits as a signed int that orders as the float does (not NaN): non-negative floats order
# as their bits already; a negative float's lower 31 bits are flipped, so larger magnitudes become
# smaller ints. The map is its own inverse. -0.0 maps below +0.0, which fmaxf may treat as equal.
_ORDERED = "(__float_as_int({v}) ^ ((__float_as_int({v}) >> 31) & 0x7fffffff))"
_FROM_ORDERED = "__int_as_float(({v}) ^ ((({v}) >> 31) & 0x7fffffff))"


@wp.func_native(_reduced("float", "fmaxf({a}, {b})", _ORDERED, _FROM_ORDERED))
def lane_max(value: float) -> float:
    """The largest ``value`` over the warp's lanes (not NaN)."""
    ...


@wp.func_native(_reduced("int", "max({a}, {b})", "{v}", "{v}"))
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
    f"""
#if defined(__CUDA_ARCH__)
    return (threadIdx.x & {WARP_SIZE - 1}) == 0;
#else
    return 1;
#endif
"""
)
def lane_leads() -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    atomicMax(reinterpret_cast<int*>(address(dest, index)), __float_as_int(value));
#else
    float* slot = address(dest, index);
    if (value > *slot) *slot = value;
#endif
"""
)
def atomic_max_nonnegative(dest: wp.array(dtype=float), index: int, value: float):
    """``dest[index] = max(dest[index], value)`` atomically, for ``value`` and ``dest[index]``
    both non-negative (+0.0 included; not NaN).

    Warp's ``atomic_max`` on float32 is a compare-and-swap loop that starts by waiting for a load
    of the slot, so a warp that calls it once per Gaussian of a tile list waits for memory each
    time. Non-negative floats order as their bit patterns do as signed integers, so CUDA's integer
    ``atomicMax`` on the bits gives the same result, and, its old value unused, is a reduction that
    the warp does not wait for. On the CPU a thread is alone: a plain compare and store.
    """
    ...


@wp.func
def lane_sum_vec2(v: wp.vec2):
    return wp.vec2(lane_sum(v[0]), lane_sum(v[1]))


@wp.func
def lane_sum_vec3(v: wp.vec3):
    return wp.vec3(lane_sum(v[0]), lane_sum(v[1]), lane_sum(v[2]))


# ------------------------------------------------------------------------------------------------
# Groups of half a warp (GROUP_SIZE lanes) that share one Gaussian: one thread per SH
# coefficient. Only the group's own lanes take part, so a group may leave early as a whole. CUDA
# only: on the CPU a thread is alone and this returns its input (kernels using it are launched on
# CUDA only).

GROUP_SIZE = WARP_SIZE // 2
# The lanes of this thread's half warp: the low or the high half of the 32-bit lane mask.
_GROUP_MASK = f"((threadIdx.x & {GROUP_SIZE}) ? 0xffff0000u : 0x0000ffffu)"
assert WARP_SIZE == 32, "_GROUP_MASK's two 16-bit halves assume a warp of 32 lanes"


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    return __shfl_sync({_GROUP_MASK}, value, lane, {GROUP_SIZE});
#else
    return value;
#endif
"""
)
def group_read(value: float, lane: int) -> float:
    """``value`` as lane ``lane`` (0 .. GROUP_SIZE - 1) of this thread's half warp holds it."""
    ...


# ------------------------------------------------------------------------------------------------
# The block of BLOCK_SIZE threads that renders one tile: the tile's next BLOCK_SIZE Gaussians in
# shared memory, as three float4 fields per Gaussian (field f of slot j at f * BLOCK_SIZE + j), so
# that a lane reads a Gaussian with 128-bit loads that the whole warp shares (one address: a
# broadcast).

BATCH_STORE = wp.constant(0)
BATCH_LOAD = wp.constant(1)
BATCH_FIELDS = 3


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    __shared__ float4 batch[{BLOCK_SIZE * BATCH_FIELDS}];
    if (op == {BATCH_STORE}) {{ batch[slot] = make_float4(value.c[0], value.c[1], value.c[2], value.c[3]); return value; }}
    float4 v = batch[slot];
    return wp::vec4(v.x, v.y, v.z, v.w);
#else
    return value;
#endif
"""
)
def tile_batch(op: int, slot: int, value: wp.vec4) -> wp.vec4:
    """One shared-memory array of float4 per block, on CUDA only: BATCH_STORE ``value`` at
    ``slot`` (returns it) or BATCH_LOAD ``slot``. Unused on the CPU (``on_cuda`` is 0 there)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    __syncthreads();
#endif
"""
)
def block_sync():
    """A barrier for the block's threads (CUDA; nothing on the CPU, where a thread is its own block)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return __syncthreads_count(flag != 0);
#else
    return flag != 0;
#endif
"""
)
def block_count(flag: int) -> int:
    """A barrier that returns how many of the block's threads passed a non-zero ``flag``."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return 1;
#else
    return 0;
#endif
"""
)
def on_cuda() -> int:
    """1 in CUDA code, 0 in CPU code: chooses between block-cooperative and per-thread paths."""
    ...


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    __shared__ int ids[{BLOCK_SIZE}];
    if (op == {BATCH_STORE}) {{ ids[slot] = value; return 0; }}
    return ids[slot];
#else
    return 0;
#endif
"""
)
def tile_ids(op: int, slot: int, value: int) -> int:
    """The batch's Gaussian ids beside ``tile_batch``: BATCH_STORE or BATCH_LOAD an int (CUDA only)."""
    ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    __shared__ int top;
    if (threadIdx.x == 0) top = value;
    __syncthreads();
    atomicMax(&top, value);
    __syncthreads();
    int result = top;
    __syncthreads();
    return result;
#else
    return value;
#endif
"""
)
def block_max_int(value: int) -> int:
    """The largest ``value`` of the block's threads (a barrier: all must call it); the value itself on the CPU."""
    ...


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    __shared__ int tops[{BLOCK_SIZE}];
    if (op == {BATCH_STORE}) {{ tops[slot] = 0; return 0.0f; }}
    if (op == {BATCH_LOAD}) return __int_as_float(tops[slot]);
    atomicMax(&tops[slot], __float_as_int(value));
    return value;
#else
    return value;
#endif
"""
)
def batch_max(op: int, slot: int, value: float) -> float:
    """A per-slot max of non-negative floats in shared memory beside ``tile_batch`` (CUDA only):
    BATCH_STORE sets ``slot`` to 0, BATCH_LOAD reads it, any other ``op`` raises it to ``value``
    (a shared-memory atomic on the float's bits, which order as the floats do when non-negative)."""
    ...


BATCH_MAX = wp.constant(2)  # batch_max's op that raises a slot


# ------------------------------------------------------------------------------------------------
# Per-Gaussian sums of the block's batch: up to 12 floats for each of the BLOCK_SIZE slots, in
# shared memory. A warp adds its lanes' values for one slot with a transposed reduction: at each of
# the first halving steps a lane keeps half of its values and trades the other half with the lane
# ``offset`` away, so 8 values take 4 + 2 + 1 shuffles (and 2 more to finish) where summing each
# over the warp takes 8 x 5; the lanes left holding a field's sum add it into the slot with
# shared-memory atomics. After the batch one thread per slot reads the sums and adds them to global
# memory once per tile, where the warps' own atomics would add them once per warp (8 per tile).

GRADIENTS_ZERO = wp.constant(0)
GRADIENTS_ADD = wp.constant(1)
GRADIENTS_READ = wp.constant(2)
# Floats per slot: 12 fields and one of padding (an odd stride keeps a slot's fields, and the
# same field of consecutive slots, in different shared-memory banks).
_GRADIENT_STRIDE = 13


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    __shared__ float sums[{BLOCK_SIZE * _GRADIENT_STRIDE}];
    float* mine = sums + slot * {_GRADIENT_STRIDE};
    if (op == {GRADIENTS_ZERO}) {{
        for (int f = 0; f < 12; ++f) mine[f] = 0.0f;
        return a;
    }}
    if (op == {GRADIENTS_READ}) {{
        return wp::vec4(mine[4 * part], mine[4 * part + 1], mine[4 * part + 2], mine[4 * part + 3]);
    }}
    const int lane = threadIdx.x & {WARP_SIZE - 1};
    // Fields 0..7 (a and b): three halving steps, then a butterfly over the last two lane bits.
    float v[8] = {{a.c[0], a.c[1], a.c[2], a.c[3], b.c[0], b.c[1], b.c[2], b.c[3]}};
    int field = 0;
    int width = 8;
    #pragma unroll
    for (int offset = 16; offset >= 4; offset >>= 1) {{
        width >>= 1;
        const int high = (lane & offset) ? 1 : 0;
        field += high * width;
        for (int i = 0; i < width; ++i) {{
            const float keep = high ? v[width + i] : v[i];
            const float send = high ? v[i] : v[width + i];
            v[i] = keep + __shfl_xor_sync({FULL_MASK}, send, offset);
        }}
    }}
    float s = v[0];
    s += __shfl_xor_sync({FULL_MASK}, s, 2);
    s += __shfl_xor_sync({FULL_MASK}, s, 1);
    if ((lane & 3) == 0) atomicAdd(mine + field, s);
    if (fields <= 9) {{
        // Field 8 (c.x) summed over the warp.
        float t = c.c[0];
        for (int offset = 16; offset > 0; offset >>= 1) t += __shfl_xor_sync({FULL_MASK}, t, offset);
        if (lane == 0) atomicAdd(mine + 8, t);
    }} else {{
        // Fields 8..11 (c): two halving steps, then a butterfly over the last three lane bits.
        float w[4] = {{c.c[0], c.c[1], c.c[2], c.c[3]}};
        int extra = 8;
        int half = 4;
        #pragma unroll
        for (int offset = 16; offset >= 8; offset >>= 1) {{
            half >>= 1;
            const int high = (lane & offset) ? 1 : 0;
            extra += high * half;
            for (int i = 0; i < half; ++i) {{
                const float keep = high ? w[half + i] : w[i];
                const float send = high ? w[i] : w[half + i];
                w[i] = keep + __shfl_xor_sync({FULL_MASK}, send, offset);
            }}
        }}
        float t = w[0];
        for (int offset = 4; offset > 0; offset >>= 1) t += __shfl_xor_sync({FULL_MASK}, t, offset);
        if ((lane & 7) == 0) atomicAdd(mine + extra, t);
    }}
    return a;
#else
    return a;
#endif
"""
)
def block_gradients(op: int, slot: int, part: int, fields: int, a: wp.vec4, b: wp.vec4, c: wp.vec4) -> wp.vec4:
    """The block's per-slot sums (CUDA only; on the CPU it returns ``a`` and keeps nothing).

    GRADIENTS_ZERO: this thread zeroes ``slot``'s 12 fields. GRADIENTS_ADD: every lane of the warp
    (all 32 must call it together) adds its ``a``, ``b`` and ``c`` to ``slot``'s fields 0-3, 4-7
    and 8-11, of which the first ``fields`` (9 or 12) are kept. GRADIENTS_READ: fields ``4 * part``
    to ``4 * part + 3`` of ``slot``. A slot is read and zeroed by the thread that owns it, after a
    barrier that follows the warps' additions.
    """
    ...
