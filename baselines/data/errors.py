"""The single exception type of the dataset readers."""
from __future__ import annotations


class DatasetError(ValueError):
    """Bad dataset input: missing or malformed file, inconsistent counts or sizes, bad values.

    The message always names the culprit (file, folder, key or argument).
    """


class EmptySplitError(DatasetError):
    """No training view is left after the train/test split (the host adds what its plugins need)."""
