"""Worked examples and the paper's problems (data made with fixed seeds)."""
