"""The MPC expert (paper section 3.2): a linear MPC on privileged state, solved with OSQP.

=================  ===============================================================
module             its one job
=================  ===============================================================
``config``         :class:`MpcConfig` (``configs/expert.toml``), every value checked
``model``          the 9-state model ``f(x, u)`` from the sim's physics, linearised
                   about hover and discretised (:func:`linearise_hover`)
``qp``             the sparse QP (layout, constraints, costs) and its solvers: OSQP,
                   Clarabel as fallback, :class:`MpcSolveError` when both fail
``controller``     :class:`MpcExpert`: ground truth in, a Command out, per step
=================  ===============================================================

The public names are re-exported here: ``from expert.mpc import MpcExpert, load_mpc_config``.
"""

from expert.mpc.config import MpcConfig, load_mpc_config
from expert.mpc.controller import MpcExpert, MpcPlan, MpcState, MpcStats
from expert.mpc.model import HoverModel, ModelInput, ModelState, linearise_hover, model_derivative
from expert.mpc.qp import MpcSolveError

__all__ = [
    "HoverModel",
    "ModelInput",
    "ModelState",
    "MpcConfig",
    "MpcExpert",
    "MpcPlan",
    "MpcSolveError",
    "MpcState",
    "MpcStats",
    "linearise_hover",
    "load_mpc_config",
    "model_derivative",
]
