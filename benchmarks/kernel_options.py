"""The renderer's kernel choices as options of a benchmark: ``--blend-backward`` and ``--blend-chunk``
(``cdcgs.render.BLEND_BACKWARD_CUDA`` and ``BLEND_CHUNK``), and ``--w-max-pass`` (how CDC-GS's Γ
pass finds w_max, ``cdcgs.complexity.W_MAX_PASS``), ``--gamma-views-per-launch`` and ``--sh-adam``
(where a replayed step takes the SH coefficients' Adam step, ``cdcgs.train.graph.FUSE_SH_ADAM``),
for timing one against another."""

from __future__ import annotations

import contextlib

import cdcgs.complexity
import cdcgs.render
import cdcgs.train.graph
from cdcgs.kernels import BLOCK_SIZE


def add_kernel_options(parser) -> None:
    parser.add_argument(
        "--blend-backward",
        choices=("block", "warp"),
        default=None,
        help="how the blend adjoint adds its sums on CUDA (cdcgs.render.BLEND_BACKWARD_CUDA; default: as it is)",
    )
    parser.add_argument(
        "--blend-chunk",
        type=int,
        default=None,
        help=f"list entries per block of the blend adjoint, a multiple of {BLOCK_SIZE} (0: whole tiles; "
        "cdcgs.render.BLEND_CHUNK; default: as it is)",
    )
    parser.add_argument(
        "--w-max-pass",
        choices=cdcgs.complexity.W_MAX_PASSES,
        default=None,
        help="how the Γ pass finds w_max under the alpha rule: each pixel walks its tile list, or each list "
        "entry scatters to its support box (cdcgs.complexity.W_MAX_PASS; default: as it is)",
    )
    parser.add_argument(
        "--sh-adam",
        choices=("adjoint", "launch"),
        default=None,
        help="where a replayed step of one view takes the SH coefficients' Adam step: in their adjoint, or in the "
        "Adam launch with the other parameters (cdcgs.train.graph.FUSE_SH_ADAM; default: as it is)",
    )
    parser.add_argument(
        "--gamma-views-per-launch",
        type=int,
        default=None,
        help="views the Γ pass measures in one launch (cdcgs.complexity.GAMMA_VIEWS_PER_LAUNCH; 1: one a launch; "
        "default: as it is)",
    )


def check_kernel_options(parser, args) -> None:
    if args.blend_chunk is not None and (args.blend_chunk < 0 or args.blend_chunk % BLOCK_SIZE):
        parser.error(f"--blend-chunk must be 0 or a multiple of {BLOCK_SIZE}, got {args.blend_chunk}")
    views = getattr(args, "gamma_views_per_launch", None)
    if views is not None and views < 1:
        parser.error(f"--gamma-views-per-launch must be at least 1, got {views}")


@contextlib.contextmanager
def kernel_options(args):
    """The renderer with ``args``' choices for the duration, as it was after."""
    before = (
        cdcgs.render.BLEND_BACKWARD_CUDA,
        cdcgs.render.BLEND_CHUNK,
        cdcgs.complexity.W_MAX_PASS,
        cdcgs.complexity.GAMMA_VIEWS_PER_LAUNCH,
        cdcgs.train.graph.FUSE_SH_ADAM,
    )
    if getattr(args, "sh_adam", None):
        cdcgs.train.graph.FUSE_SH_ADAM = args.sh_adam == "adjoint"
    if getattr(args, "gamma_views_per_launch", None):
        cdcgs.complexity.GAMMA_VIEWS_PER_LAUNCH = args.gamma_views_per_launch
    if getattr(args, "w_max_pass", None):
        cdcgs.complexity.W_MAX_PASS = args.w_max_pass
    if args.blend_backward:
        cdcgs.render.BLEND_BACKWARD_CUDA = args.blend_backward
    if args.blend_chunk is not None:
        cdcgs.render.BLEND_CHUNK = args.blend_chunk
    try:
        yield
    finally:
        (
            cdcgs.render.BLEND_BACKWARD_CUDA,
            cdcgs.render.BLEND_CHUNK,
            cdcgs.complexity.W_MAX_PASS,
            cdcgs.complexity.GAMMA_VIEWS_PER_LAUNCH,
            cdcgs.train.graph.FUSE_SH_ADAM,
        ) = before
