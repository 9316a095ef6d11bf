"""Samplers: initial falling states, end poses, disturbances."""
