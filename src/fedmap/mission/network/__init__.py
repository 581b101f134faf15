"""Nodes, frames and transports: the link model (``link``), who talks to whom and how a
round goes (``topology``), fedmap's frames (``wire``), what each node logs of itself
(``nodelog``) and nodes on processes of their own (``remote``).
"""
