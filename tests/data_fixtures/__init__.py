"""Generators of tiny dataset fixtures (written at test time; no binary data is committed)."""
