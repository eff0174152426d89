"""3DGS-MCMC's perturbation of the means, as one kernel.

Pure Warp. After every optimizer step 3DGS-MCMC moves each mean by

    Σ z · sigmoid(-k (o - t)) · scale,    Σ = R diag(s²) Rᵀ,

with z ~ N(0, I) drawn by the caller (so that its generator decides the draws), R the rotation of
the Gaussian's quaternion (w, x, y, z; normalised here), s = exp(log-scales), o = sigmoid(opacity
logit) and ``scale`` = noise_lr · lr: Langevin exploration for transparent Gaussians, almost none
for opaque ones. One thread per Gaussian reads its parameters and adds its noise to ``means_out``:
the means themselves, or zeros to get the noise. Built in torch the same takes about 50 small
kernels a step (the rotation, the covariance, two batched 3 × 3 products, the gate).
"""

import warp as wp

from .projection import quat_to_rotation

__all__ = ["mcmc_noise_kernel"]

wp.set_module_options({"fast_math": False})


@wp.kernel(enable_backward=False)
def mcmc_noise_kernel(
    quats: wp.array(dtype=wp.vec4),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=float),
    z: wp.array(dtype=wp.vec3),
    k: float,
    t: float,
    scale: float,
    halt: wp.array(dtype=wp.int32),
    means_out: wp.array(dtype=wp.vec3),
):
    """``means_out[i] += R diag(s²) Rᵀ z[i] · sigmoid(-k (o - t)) · scale`` of Gaussian ``i`` (dim = N);
    nothing while ``halt[0]`` is non-zero (``halt`` empty: never; see ``fused_adam_kernel``)."""
    i = wp.tid()
    if halt.shape[0] > 0:
        if halt[0] != 0:
            return
    rotation = quat_to_rotation(quats[i])  # the projection's: (w, x, y, z), normalised
    s = log_scales[i]
    variance = wp.vec3(wp.exp(2.0 * s[0]), wp.exp(2.0 * s[1]), wp.exp(2.0 * s[2]))
    local = wp.transpose(rotation) * z[i]
    opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
    gate = 1.0 / (1.0 + wp.exp(k * (opacity - t)))
    means_out[i] = means_out[i] + rotation * wp.cw_mul(variance, local) * (gate * scale)
