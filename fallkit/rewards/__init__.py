"""Reward terms (paper Table I), each a small pure function of a batch context."""
