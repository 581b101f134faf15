"""fedmap's exceptions.

Anything a user can get wrong (a missing file, a bad shape, a typo in an option)
raises :class:`FedmapError` with a one-line message. The CLI prints that line and
exits non-zero without a traceback; programming errors still raise normally.

:class:`RejectedUpdate` is the one error a federated round survives: a rover's update
that must be left out of the round (its training diverged, its weights are not finite,
its map has nothing to train on, or its payload does not decode). The round aggregates
the other rovers and records why this one was dropped; every other error stops the run.
"""


class FedmapError(Exception):
    """A user-facing error with a one-line message."""


class RejectedUpdate(FedmapError):
    """A rover's update that its round leaves out (the reason is the message)."""
