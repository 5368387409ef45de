"""Plants that several test areas share, as ``[plant]`` config sections.

:data:`PLANT_3`: a 3-state plant, a damped axis behind a current loop's lag, whose output mixes
two states (``C = [1, 0.001, 0]``). It takes the general (not the 2-state) paths of the simulated
drives; its ``position()`` is a ``math.fsum``, which raises ValueError on +inf and -inf terms.
"""

from __future__ import annotations

A_3 = [[0.0, 1.0, 0.0], [0.0, -50.0, 3000.0], [0.0, 0.0, -2000.0]]
B_3 = [[0.0], [0.0], [2000.0]]
C_3 = [[1.0, 0.001, 0.0]]
PLANT_3: dict[str, object] = {"A": A_3, "B": B_3, "C": C_3, "state_names": None}
