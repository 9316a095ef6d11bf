"""fallkit-go1: the Unitree Go1 quadruped as a fallkit robot plugin (see robot.py)."""
