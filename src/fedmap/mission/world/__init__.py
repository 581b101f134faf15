"""The world the team moves in: driving, sensing and planning (``world``, ``flight``,
``sensing``, ``frontiers``), a rover fed by its own mapping software (``feed``), and rovers
that do not know their poses (``frames``).
"""
