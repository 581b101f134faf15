"""The strategies' ends: what each side of a strategy holds and sends (``protocol``), each
strategy's ends (``raw``, ``predictive``, ``model``, ``gossip``, ``rosgrid``) and the catalogue
of strategies and what each can do (``registry``).
"""
