"""dstereo: differentiable stereo photogrammetry in JAX."""

import jax

# Calibration needs float64 everywhere: enable it before any array is created.
jax.config.update("jax_enable_x64", True)

from dstereo.errors import DstereoError  # noqa: E402

__all__ = ["DstereoError"]
__version__ = "0.1.0"
