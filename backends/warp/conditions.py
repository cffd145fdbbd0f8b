"""Warp kernels of the adverse-condition models. Placeholder until filled in."""


class WarpConditions:
    """Mixin of condition kernels for the Warp backend."""
