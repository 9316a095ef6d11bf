"""Samplers of the falling environment: initial falling states (Table II) and disturbances (Table IV)."""
