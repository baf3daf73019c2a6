"""The one error type of the io wing."""
from __future__ import annotations

__all__ = ["IngestError"]


class IngestError(Exception):
    """A source that cannot be read or opened at all.  ``str(err)`` is a one-line message for the user."""
