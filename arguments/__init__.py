"""Typed parameter groups (4DGS names and defaults) and the 4DGS-style config-file loader."""
