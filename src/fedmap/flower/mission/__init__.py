"""Flower adapters of a mission on processes (``fedmap mission --deploy``): the rover's
ClientApp (``client``), the base station's ServerApp (``server``), what they do between
messages (``task``), the launcher (``deploy``) and their Flower App (``app/``). Flower carries
the star only: every message goes through the base's SuperLink.
"""
