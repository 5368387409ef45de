"""Control design of Lee, Kim, Baek (ACC 2000): ZOH + input-delay augmentation, the estimator and
feedback DAREs, the disturbance-observer gain, the Theorem-1 stability check and the loop analysis.

Public API used by the rest of dob_hil::

    from dob_hil.design import Design, build_design, sensitivity_response

Importing this package loads numpy only; scipy, python-control and matplotlib are imported inside
the functions that need them.
"""

from __future__ import annotations

from dob_hil.design.artifact import FORMAT_VERSION, Design
from dob_hil.design.build import DesignResult, build_design, design_with_diagnostics
from dob_hil.design.loops import sensitivity_response

__all__ = [
    "FORMAT_VERSION",
    "Design",
    "DesignResult",
    "build_design",
    "design_with_diagnostics",
    "sensitivity_response",
]
