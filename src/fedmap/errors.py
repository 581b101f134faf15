"""The one exception type for user mistakes.

Anything a user can get wrong (a missing file, a bad shape, a typo in an option)
raises :class:`FedmapError` with a one-line message. The CLI prints that line and
exits non-zero without a traceback; programming errors still raise normally.
"""


class FedmapError(Exception):
    """A user-facing error with a one-line message."""
