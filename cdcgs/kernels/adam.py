"""Adam for the Gaussians' parameters: every parameter in one launch, and on selected rows.

Pure Warp. A parameter is a flat float32 array of ``rows * row_width`` values (one row per
Gaussian: 3 for the means, 45 for the SH coefficients past degree 0, ...) with its gradient and
Adam's two moments laid out alike. Both kernels apply torch's Adam update (``torch.optim.Adam``,
no weight decay, no amsgrad) through one function, ``adam_update``:

- ``fused_adam_kernel`` updates several parameters in one launch (``dim`` = their total number
  of values), each with its own rates and step count, read from two small tables. torch's
  fused Adam launches at least once per parameter group, and a 3DGS model has six groups (one
  learning rate each).
- ``selective_adam_kernel`` updates one parameter (``dim=rows * row_width``).

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

__all__ = ["fused_adam_kernel", "selective_adam_kernel"]

wp.set_module_options({"fast_math": False})


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
    """One Adam step of value ``i``: m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2,
    p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps), as torch computes it (bc = 1 - b^step).
    ``one_minus_beta1`` and ``one_minus_beta2`` are 1 - b computed by the caller in double
    precision, as torch's Adam passes them (1 - float32(0.999) is 1.3e-5 off)."""
    g = grad[i]
    m = beta1 * exp_avg[i] + one_minus_beta1 * g
    v = beta2 * exp_avg_sq[i] + one_minus_beta2 * g * g
    exp_avg[i] = m
    exp_avg_sq[i] = v
    param[i] = param[i] - (lr / bias_correction1) * m / (wp.sqrt(v) / bias_correction2_sqrt + eps)


@wp.kernel(enable_backward=False)
def fused_adam_kernel(
    parameters: wp.array2d(dtype=wp.int64),
    rates: wp.array2d(dtype=float),
    selected: wp.array(dtype=wp.uint8),
    halt: wp.array(dtype=wp.int32),
):
    """One Adam step of every parameter of the tables, one thread per value; nothing while
    ``halt[0]`` is non-zero (``halt`` empty: never).

    Row ``k`` of ``parameters`` [P, 7] describes parameter ``k``: the addresses of its value,
    gradient, exp_avg and exp_avg_sq arrays (float32, contiguous), then the first launch index it
    owns, its number of values and its values per row. The parameters own the launch indices in
    order and without gaps: the first starts at 0 and the launch's ``dim`` is the sum of the counts.
    ``rates[k]`` [P, 8]: lr, beta1, beta2, 1 - beta1, 1 - beta2, eps, bias_correction1 and
    bias_correction2_sqrt, as the arguments of ``selective_adam_kernel``. ``selected``: one entry
    per row shared by every parameter, or empty for every row. (One int64 table and one float
    table: two small copies to the device a step.)"""
    i = wp.tid()
    if halt.shape[0] > 0:
        if halt[0] != 0:
            return
    k = int(0)
    while k + 1 < parameters.shape[0] and i >= int(parameters[k + 1, 4]):
        k += 1
    local = i - int(parameters[k, 4])
    if selected.shape[0] > 0:
        if selected[local // int(parameters[k, 6])] == wp.uint8(0):
            return
    count = int(parameters[k, 5])
    adam_update(
        wp.array(ptr=wp.uint64(parameters[k, 0]), shape=(count,), dtype=float),
        wp.array(ptr=wp.uint64(parameters[k, 1]), shape=(count,), dtype=float),
        wp.array(ptr=wp.uint64(parameters[k, 2]), shape=(count,), dtype=float),
        wp.array(ptr=wp.uint64(parameters[k, 3]), shape=(count,), dtype=float),
        local,
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
