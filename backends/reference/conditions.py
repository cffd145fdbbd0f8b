"""Reference (NumPy float64) kernels of the adverse-condition models. Placeholder until filled in."""


class ReferenceConditions:
    """Mixin of condition kernels for the reference backend."""
