"""Importing this module switches JAX to float64: stiff thermal networks need it."""

import jax

jax.config.update("jax_enable_x64", True)
