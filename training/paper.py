"""The paper's own numbers (cited by section), typed once for the report and the model card."""

from __future__ import annotations

__all__ = ["PAPER_RUNTIME_S", "PAPER_TABLE3", "PAPER_VISION_TERMINAL_SPEED_M_S"]

PAPER_TABLE3: dict[str, dict[str, float]] = {
    "bc": {"min": 1.56, "max": 10.47, "mean": 5.74, "std": 2.14},
    "dagger": {"min": 0.56, "max": 0.91, "mean": 0.70, "std": 0.09},
    "vision": {"min": 0.54, "max": 1.27, "mean": 0.84, "std": 0.21},
}
"""Paper section 5.4, Table 3 "Landing Performance Metrics": landing error in m. The paper has
no expert row and reports neither touchdown speed nor success rate there (section 5.5 says only,
from its Figure 6, that the vision policy's terminal velocity is "approximately 5 m/s")."""

PAPER_VISION_TERMINAL_SPEED_M_S = 5.0
"""Paper section 5.5 (qualitative, read off its Figure 6): the vision policy's terminal velocity."""

PAPER_RUNTIME_S: dict[str, float] = {
    "mpc_mean": 0.125,
    "mpc_std": 0.025,
    "policy_mean": 0.0132,
    "policy_std": 0.0014,
}
"""Paper section 6 "Runtime Efficiency": seconds per control input, MPC expert vs CNN+LSTM."""
