"""The one exception of `prepare`: a message for the user and what to try next."""
from __future__ import annotations


class PrepareError(RuntimeError):
    """A failure of `python -m baselines.prepare` that the user can act on.

    `str(error)` is ONE line: what went wrong and, when there is one, what to try
    (`hint`). The command line prints it as `error: ...` and exits with code 2, no traceback.
    """

    def __init__(self, message: str, hint: str | None = None):
        self.message = message
        self.hint = hint
        super().__init__(f"{message}; try: {hint}" if hint else message)
