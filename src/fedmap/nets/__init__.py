"""Networks and local training: the coordinate networks, ``fit``, and where they start."""
