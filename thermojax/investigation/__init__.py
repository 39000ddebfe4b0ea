"""The missing-physics loop: residual diagnostics, candidate effects, `investigate`,
`diagnose` and their report."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._diagnose import diagnose
from ._investigate import investigate
from ._step import evaluate

__all__ = ["diagnose", "evaluate", "investigate"]
