"""Adam on the rows of a parameter that a mask selects: "selective Adam".

Pure Warp. A parameter is a flat float32 array of ``rows * row_width`` values (one row per
Gaussian: 3 for the means, 48 for the SH coefficients past degree 0, ...) with its gradient and
Adam's two moments laid out alike. ``selective_adam_kernel`` (``dim=rows * row_width``) applies
torch's Adam update (``torch.optim.Adam``, no weight decay, no amsgrad) to the values of the rows
whose ``selected`` entry is non-zero and leaves every other row, parameter and moments, as it is.
With every row selected it is Adam.

Leaving the moments of unselected rows undecayed is the point and the approximation: a Gaussian
that the view does not see neither moves nor forgets (Taming 3DGS's and gsplat's SelectiveAdam),
where Adam would still move it by its momentum.
"""

import warp as wp

__all__ = ["selective_adam_kernel"]

wp.set_module_options({"fast_math": False})


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
    """One Adam step of the selected rows: m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2,
    p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps), as torch computes it (bc = 1 - b^step).
    ``one_minus_beta1`` and ``one_minus_beta2`` are 1 - b computed by the caller in double
    precision, as torch's Adam passes them (1 - float32(0.999) is 1.3e-5 off)."""
    i = wp.tid()
    if selected[i // row_width] == wp.uint8(0):
        return
    g = grad[i]
    m = beta1 * exp_avg[i] + one_minus_beta1 * g
    v = beta2 * exp_avg_sq[i] + one_minus_beta2 * g * g
    exp_avg[i] = m
    exp_avg_sq[i] = v
    param[i] = param[i] - (lr / bias_correction1) * m / (wp.sqrt(v) / bias_correction2_sqrt + eps)
