"""The standard fall strategies the paper compares against (Sec. V-C).

Each holds the most recent setpoint (the joint angles when the fall begins)
with the nominal PD gains scaled per world:
  zero_torque  actuators off (gains x 0)
  damping      low gains (x 0.1): compliant
  freeze       high gains (x 10): the robot falls as one rigid body
"""

from __future__ import annotations

STRATEGIES: dict[str, float] = {"zero_torque": 0.0, "damping": 0.1, "freeze": 10.0}
