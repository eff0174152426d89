"""Numbers shared by the kernels and their callers, as plain Python values (no Warp, no torch).

Warp kernels read module-level Python numbers as compile-time constants, and torch code can import
them without Warp; this module is the one place they are written.
"""

__all__ = [
    "BLOCK_SIZE",
    "MAX_SH_COEFFICIENTS",
    "MAX_SH_DEGREE",
    "SH_C0",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "TILE_SIZE",
]

# Side of the square pixel tiles that binning sorts Gaussians into, in pixels.
TILE_SIZE = 16
# Threads of a blend or complexity block: one per pixel of a tile (launch with block_dim=BLOCK_SIZE).
BLOCK_SIZE = TILE_SIZE * TILE_SIZE

# Real spherical harmonics up to degree 3, 3DGS's sign convention: the basis of degree 0 is SH_C0,
# of degree 1 (-SH_C1 y, SH_C1 z, -SH_C1 x), of degree 2 SH_C2[k] times (xy, yz, 2z^2 - x^2 - y^2,
# xz, x^2 - y^2), of degree 3 SH_C3[k] times (y(3x^2 - y^2), xyz, y(4z^2 - x^2 - y^2),
# z(2z^2 - 3x^2 - 3y^2), x(4z^2 - x^2 - y^2), z(x^2 - y^2), x(x^2 - 3y^2)), for a unit direction
# (x, y, z) from the camera centre to the Gaussian.
MAX_SH_DEGREE = 3
MAX_SH_COEFFICIENTS = (MAX_SH_DEGREE + 1) ** 2
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
