"""Hydra configs (a package so that Hydra finds them when fallkit is installed)."""
