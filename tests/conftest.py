"""Test configuration: float64 everywhere and strict rank promotion (style.md section 7)."""

import jax
import matplotlib

matplotlib.use("Agg")
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
