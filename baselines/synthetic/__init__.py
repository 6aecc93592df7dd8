"""Synthetic dynamic-scene simulator with its own analytic renderer and full ground truth."""
