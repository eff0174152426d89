"""Adam for the Gaussians' parameters: every parameter in one launch, and on selected rows.

Pure Warp. A parameter is a flat float32 array of ``rows * row_width`` values (one row per
Gaussian: 3 for the means, 45 for the SH coefficients past degree 0, ...) with its gradient and
Adam's two moments laid out alike. Both kernels apply torch's Adam update (``torch.optim.Adam``,
no weight decay, no amsgrad) with one arithmetic, ``adam_update``'s:

- ``fused_adam_kernel`` updates several parameters in one launch, each with its own rates and step
  count, read from two small tables. torch's fused Adam launches at least once per parameter
  group, and a 3DGS model has six groups (one learning rate each). A thread updates a quad, four
  consecutive values of one parameter (``VALUES_PER_THREAD``), on CUDA with one 128-bit load and
  store per array where it can (a prototype on an H100 at 1M Gaussians, 2026-11-27: 0.555 ms a
  launch against 0.683 with one value a thread, 2.98 against 2.42 TB/s); ``dim`` = the sum of the
  parameters' ``adam_quads``.
- ``selective_adam_kernel`` updates one parameter, one value a thread (``dim=rows * row_width``).

Both take ``selected``, one entry per row: a row whose entry is 0 keeps its values and both
moments ("selective Adam"; ``fused_adam_kernel`` with an empty ``selected`` updates every row).
``fused_adam_kernel`` also takes ``halt``, a device flag: while ``halt[0]`` is non-zero it changes
nothing (a training that renders without reading its counts sets it when a render overflowed, and
steps again once the host has seen it; :mod:`cdcgs.train.lookahead`). An empty ``halt`` never halts.
Leaving the moments of unselected rows undecayed is the point and the approximation: a Gaussian
that the view does not see neither moves nor forgets (Taming 3DGS's and gsplat's SelectiveAdam),
where Adam would still move it by its momentum.
"""

import warp as wp

__all__ = [
    "VALUES_PER_THREAD",
    "AdamStep",
    "adam_quads",
    "adam_rates",
    "adam_step_halted",
    "adam_step_rates",
    "adam_step_value",
    "adam_step_with",
    "fused_adam_kernel",
    "selective_adam_kernel",
]

wp.set_module_options({"fast_math": False})

# Values of one parameter that a thread of fused_adam_kernel updates: a float4 (adam_update_quad).
VALUES_PER_THREAD = wp.constant(4)


def adam_quads(count: int) -> int:
    """Threads of ``fused_adam_kernel`` for a parameter of ``count`` values: one per quad of
    VALUES_PER_THREAD consecutive values, the last one possibly partial. A parameter's first launch
    index is the sum of the quads of those before it, and the launch's ``dim`` the sum of all."""
    return -(-count // VALUES_PER_THREAD)


@wp.func
def adam_value(
    p: float,
    g: float,
    m: float,
    v: float,
    lr: float,
    beta1: float,
    beta2: float,
    one_minus_beta1: float,
    one_minus_beta2: float,
    eps: float,
    bias_correction1: float,
    bias_correction2_sqrt: float,
):
    """One Adam step of one value ``p`` with gradient ``g`` and moments ``m``, ``v``: (new p, new m,
    new v). m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2, p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2)
    + eps), as torch computes it (bc = 1 - b^step). ``one_minus_beta1`` and ``one_minus_beta2`` are
    1 - b computed by the caller in double precision, as torch's Adam passes them (1 - float32(0.999)
    is 1.3e-5 off). ``adam_update_quad`` repeats it in CUDA C, operation for operation: change both
    together."""
    m = beta1 * m + one_minus_beta1 * g
    v = beta2 * v + one_minus_beta2 * g * g
    p = p - (lr / bias_correction1) * m / (wp.sqrt(v) / bias_correction2_sqrt + eps)
    return wp.vec3(p, m, v)


@wp.func
def adam_update(
    param: wp.array(dtype=float),
    grad: wp.array(dtype=float),
    exp_avg: wp.array(dtype=float),
    exp_avg_sq: wp.array(dtype=float),
    i: int,
    lr: float,
    beta1: float,
    beta2: float,
    one_minus_beta1: float,
    one_minus_beta2: float,
    eps: float,
    bias_correction1: float,
    bias_correction2_sqrt: float,
):
    """``adam_value`` of value ``i`` of the arrays, in place."""
    out = adam_value(
        param[i],
        grad[i],
        exp_avg[i],
        exp_avg_sq[i],
        lr,
        beta1,
        beta2,
        one_minus_beta1,
        one_minus_beta2,
        eps,
        bias_correction1,
        bias_correction2_sqrt,
    )
    exp_avg[i] = out[1]
    exp_avg_sq[i] = out[2]
    param[i] = out[0]


@wp.struct
class AdamStep:
    """One Adam step of one parameter, for a kernel that applies it where it would write the
    parameter's gradient (the SH adjoint of a replayed training step,
    :func:`cdcgs.render.sh_adjoint`): the parameter and its two moments as flat float32 arrays,
    ``rates`` (``fused_adam_kernel``'s rates table, on the device) and the row of it that holds this
    parameter's, and ``halt`` (int32; while ``halt[0]`` is non-zero nothing changes; empty: never).
    ``radii`` (not empty: selective Adam) the view's radii, one per row of ``row_width`` values:
    only the rows whose two radii are positive (the Gaussians the view sees) are stepped, the others
    keep their values and moments. An empty ``param`` means no step: the kernel writes the gradient
    instead."""

    param: wp.array(dtype=float)
    exp_avg: wp.array(dtype=float)
    exp_avg_sq: wp.array(dtype=float)
    rates: wp.array2d(dtype=float)
    row: int
    halt: wp.array(dtype=wp.int32)
    radii: wp.array(dtype=wp.vec2i)
    row_width: int


# An AdamStep's row of the rates table: lr, beta1, beta2, 1 - beta1, 1 - beta2, eps, bias
# correction 1, sqrt of bias correction 2 (``adam_value``'s arguments after the moments).
adam_rates = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def adam_step_rates(step: AdamStep):
    """``step``'s rates, read once. A kernel that steps many values reads them before its loop:
    inside it they would be read again after every store, which the compiler cannot tell apart
    from the rates table."""
    r = step.row
    return adam_rates(
        step.rates[r, 0],
        step.rates[r, 1],
        step.rates[r, 2],
        step.rates[r, 3],
        step.rates[r, 4],
        step.rates[r, 5],
        step.rates[r, 6],
        step.rates[r, 7],
    )


@wp.func
def adam_step_halted(step: AdamStep) -> int:
    """1 while ``step``'s halt flag is set (nothing may change), else 0."""
    if step.halt.shape[0] > 0:
        if step.halt[0] != 0:
            return 1
    return 0


@wp.func
def adam_step_with(step: AdamStep, rates: adam_rates, i: int, g: float):
    """``adam_value`` of value ``i`` of ``step``'s parameter with gradient ``g`` and ``rates`` (from
    :func:`adam_step_rates`), in place, unless (selective) its row is not selected. The caller has
    checked :func:`adam_step_halted`."""
    if step.radii.shape[0] > 0:
        radius = step.radii[i // step.row_width]
        if radius[0] <= 0 or radius[1] <= 0:
            return
    out = adam_value(
        step.param[i],
        g,
        step.exp_avg[i],
        step.exp_avg_sq[i],
        rates[0],
        rates[1],
        rates[2],
        rates[3],
        rates[4],
        rates[5],
        rates[6],
        rates[7],
    )
    step.exp_avg[i] = out[1]
    step.exp_avg_sq[i] = out[2]
    step.param[i] = out[0]


@wp.func
def adam_step_value(step: AdamStep, i: int, g: float):
    """``adam_value`` of value ``i`` of ``step``'s parameter with gradient ``g``, in place, unless
    its halt flag is set or (selective) its row is not selected."""
    if adam_step_halted(step) == 0:
        adam_step_with(step, adam_step_rates(step), i, g)


@wp.func_native(
    """
    // adam_value's arithmetic, operation for operation
    auto update = [&](float g, float& p, float& m, float& v) {
        m = beta1 * m + one_minus_beta1 * g;
        v = beta2 * v + one_minus_beta2 * g * g;
        p = p - (lr / bias_correction1) * m / (::sqrtf(v) / bias_correction2_sqrt + eps);
    };
#if !defined(__CUDA_ARCH__)
    // The CPU: value by value.
    float* p = reinterpret_cast<float*>(param) + 4 * static_cast<long long>(quad);
    float* m = reinterpret_cast<float*>(exp_avg) + 4 * static_cast<long long>(quad);
    float* v = reinterpret_cast<float*>(exp_avg_sq) + 4 * static_cast<long long>(quad);
    const float* g = reinterpret_cast<const float*>(grad) + 4 * static_cast<long long>(quad);
    for (int j = 0; j < 4; ++j) {
        update(g[j], p[j], m[j], v[j]);
    }
#else
    float4* values = reinterpret_cast<float4*>(param) + quad;
    float4* moments = reinterpret_cast<float4*>(exp_avg) + quad;
    float4* squares = reinterpret_cast<float4*>(exp_avg_sq) + quad;
    const float4 g = reinterpret_cast<const float4*>(grad)[quad];
    float4 p = *values, m = *moments, v = *squares;
    update(g.x, p.x, m.x, v.x);
    update(g.y, p.y, m.y, v.y);
    update(g.z, p.z, m.z, v.z);
    update(g.w, p.w, m.w, v.w);
    *moments = m;
    *squares = v;
    *values = p;
#endif
"""
)
def adam_update_quad(
    param: wp.uint64,
    grad: wp.uint64,
    exp_avg: wp.uint64,
    exp_avg_sq: wp.uint64,
    quad: int,
    lr: float,
    beta1: float,
    beta2: float,
    one_minus_beta1: float,
    one_minus_beta2: float,
    eps: float,
    bias_correction1: float,
    bias_correction2_sqrt: float,
):
    """``adam_update`` of values 4 ``quad`` .. 4 ``quad`` + 3 of the float32 arrays at these
    addresses (16-byte aligned), on CUDA with one 128-bit load and store per array; on the CPU
    value by value (so that the CPU tests take the same branches as CUDA)."""
    ...


@wp.kernel(enable_backward=False)
def fused_adam_kernel(
    parameters: wp.array2d(dtype=wp.int64),
    rates: wp.array2d(dtype=float),
    selected: wp.array(dtype=wp.uint8),
    halt: wp.array(dtype=wp.int32),
):
    """One Adam step of every parameter of the tables, one thread per quad (VALUES_PER_THREAD
    consecutive values of one parameter); nothing while ``halt[0]`` is non-zero (``halt`` empty:
    never).

    Row ``k`` of ``parameters`` [P, 7] describes parameter ``k``: the addresses of its value,
    gradient, exp_avg and exp_avg_sq arrays (float32, contiguous), then the first launch index it
    owns (a quad index), its number of values and its values per row. The parameters own the launch
    indices in order and without gaps: the first starts at 0, each next one ``adam_quads(count)``
    after it, and the launch's ``dim`` is the sum of their ``adam_quads``. ``rates[k]`` [P, 8]: lr,
    beta1, beta2, 1 - beta1, 1 - beta2, eps, bias_correction1 and bias_correction2_sqrt, as the
    arguments of ``selective_adam_kernel``. ``selected``: one entry per row shared by every
    parameter, or empty for every row. (One int64 table and one float table: two small copies to
    the device a step.) A quad of four values in 16-byte aligned arrays, with every row it touches
    selected (or no ``selected``), goes through ``adam_update_quad`` (on CUDA 128-bit loads and
    stores); any other quad value by value through ``adam_update``: the same arithmetic either way,
    and the same branches on the CPU as on CUDA."""
    i = wp.tid()
    if halt.shape[0] > 0:
        if halt[0] != 0:
            return
    k = int(0)
    while k + 1 < parameters.shape[0] and i >= int(parameters[k + 1, 4]):
        k += 1
    quad = i - int(parameters[k, 4])
    count = int(parameters[k, 5])
    row_width = int(parameters[k, 6])
    first = quad * VALUES_PER_THREAD
    # 128-bit accesses need four whole values and 16-byte aligned arrays (a view of a larger
    # array may start anywhere), and under a mask the quad's rows all selected (none: nothing to
    # do; some: value by value)
    addresses = parameters[k, 0] | parameters[k, 1] | parameters[k, 2] | parameters[k, 3]
    whole = quad < count // VALUES_PER_THREAD and addresses % wp.int64(16) == wp.int64(0)
    if whole and selected.shape[0] > 0:
        taken = int(0)
        rows = int(0)
        for row in range(first // row_width, (first + VALUES_PER_THREAD - 1) // row_width + 1):
            rows += 1
            if selected[row] != wp.uint8(0):
                taken += 1
        if taken == 0:
            return
        if taken < rows:
            whole = False
    if whole:
        adam_update_quad(
            wp.uint64(parameters[k, 0]),
            wp.uint64(parameters[k, 1]),
            wp.uint64(parameters[k, 2]),
            wp.uint64(parameters[k, 3]),
            quad,
            rates[k, 0],
            rates[k, 1],
            rates[k, 2],
            rates[k, 3],
            rates[k, 4],
            rates[k, 5],
            rates[k, 6],
            rates[k, 7],
        )
        return
    param = wp.array(ptr=wp.uint64(parameters[k, 0]), shape=(count,), dtype=float)
    grad = wp.array(ptr=wp.uint64(parameters[k, 1]), shape=(count,), dtype=float)
    exp_avg = wp.array(ptr=wp.uint64(parameters[k, 2]), shape=(count,), dtype=float)
    exp_avg_sq = wp.array(ptr=wp.uint64(parameters[k, 3]), shape=(count,), dtype=float)
    end = first + wp.min(VALUES_PER_THREAD, count - first)  # not first + 4: count may be 2^31 - 1
    for value in range(first, end):
        if selected.shape[0] > 0:
            if selected[value // row_width] == wp.uint8(0):
                continue
        adam_update(
            param,
            grad,
            exp_avg,
            exp_avg_sq,
            value,
            rates[k, 0],
            rates[k, 1],
            rates[k, 2],
            rates[k, 3],
            rates[k, 4],
            rates[k, 5],
            rates[k, 6],
            rates[k, 7],
        )


@wp.kernel(enable_backward=False)
def selective_adam_kernel(
    param: wp.array(dtype=float),
    grad: wp.array(dtype=float),
    exp_avg: wp.array(dtype=float),
    exp_avg_sq: wp.array(dtype=float),
    selected: wp.array(dtype=wp.uint8),
    row_width: int,
    lr: float,
    beta1: float,
    beta2: float,
    one_minus_beta1: float,
    one_minus_beta2: float,
    eps: float,
    bias_correction1: float,
    bias_correction2_sqrt: float,
):
    """One Adam step (``adam_update``) of the rows of one parameter whose ``selected`` entry is
    non-zero."""
    i = wp.tid()
    if selected[i // row_width] == wp.uint8(0):
        return
    adam_update(
        param,
        grad,
        exp_avg,
        exp_avg_sq,
        i,
        lr,
        beta1,
        beta2,
        one_minus_beta1,
        one_minus_beta2,
        eps,
        bias_correction1,
        bias_correction2_sqrt,
    )
