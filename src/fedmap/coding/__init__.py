"""The lossless map coders, in one place.

* :mod:`~fedmap.coding.mapcodec`: the ``context`` codec of a class map (every cell coded
  from its causal neighbours, optionally against a reference map the receiver holds),
  ``raw``'s payload;
* :mod:`~fedmap.coding.streamcodec`: the predictive stream coder of ``predictive``:
  trails, targets and the cells a receiver derives from them, coded with a probability
  model (:class:`~fedmap.coding.streamcodec.CoderState`) both ends keep from message to
  message, and its learned initial state (``fedmap/weights/cell_prior.npz``,
  :func:`~fedmap.coding.streamcodec.initial_state`); optionally with a guess both ends
  compute alike (the map predictor's P(impassable)) as one more context of every cell
  (:func:`~fedmap.coding.streamcodec.guessing_state`, ``docs/predictor.md``).

The ends that speak them over a mission's link are in :mod:`fedmap.mission.ends.raw` and
:mod:`fedmap.mission.ends.predictive`; the byte layouts are in ``docs/protocol.md``.
"""
