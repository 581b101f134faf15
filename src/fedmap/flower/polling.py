"""Flower's waits, shortened for missions: a mission sends a message to every rover at every
sync, so the seconds Flower 1.41 waits between polls are most of a round.

Flower pulls a message's objects with a backoff that starts at 1 s
(``flwr.supercore.constant.PULL_INITIAL_BACKOFF``): an object not stored yet at the first
try (the usual case right after a message is announced) costs a second per message, on the
rover (its ClientApp pulling its task) and on the base (pulling a reply).
:func:`quick_pulls` starts that backoff at ``first`` seconds instead, in this process.
"""

from __future__ import annotations

from flwr.supercore.inflatable import inflatable_utils

#: Seconds before the first retry of an object pull (Flower's own: 1 s), and the cap (10 s).
FIRST_RETRY, RETRY_CAP = 0.02, 1.0


def quick_pulls(first: float = FIRST_RETRY, cap: float = RETRY_CAP) -> None:
    """Start Flower's object-pull backoff at ``first`` s, capped at ``cap`` s, in this process."""
    for fn in (inflatable_utils.pull_objects, inflatable_utils.pull_and_inflate_object_from_tree):
        kw = fn.__kwdefaults__
        assert kw is not None and "initial_backoff" in kw, f"Flower's {fn.__name__} changed"
        kw["initial_backoff"], kw["backoff_cap"] = first, cap
