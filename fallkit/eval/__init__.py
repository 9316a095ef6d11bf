"""Evaluation: standard strategies, paired rollouts, the paper's metrics, reports, plots, videos, contact sheets."""
