"""Robots: the RobotSpec model and the built-in robots."""
