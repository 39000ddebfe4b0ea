"""Time: exact discretization, simulation (exact hold, diffrax), ETD2 for nonlinear
effects (ETDRK4 in the extended Kalman filter), and forward sensitivities for the fit's
Jacobian."""

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
from ._discretize import (AbstractDiscretization, ForwardEuler, MatrixExponential, Modal, Tustin,
                          discretize, discretize_process_noise)
from ._simulate import (AbstractSimulator, DiffraxSimulator, ExactHold, Solution, simulate,
                        simulate_batch, steady_state)

__all__ = [
    "AbstractDiscretization", "AbstractSimulator", "DiffraxSimulator", "ExactHold",
    "ForwardEuler", "MatrixExponential", "Modal", "Solution", "Tustin", "discretize",
    "discretize_process_noise", "simulate", "simulate_batch", "steady_state",
]
