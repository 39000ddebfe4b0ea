"""The command line, the config runner and the demo: no maths here."""

from ._demo import demo_runs
from ._main import main
from ._runner import perturbed, run_config

__all__ = ["demo_runs", "main", "perturbed", "run_config"]
