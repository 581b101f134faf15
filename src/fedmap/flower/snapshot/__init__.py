"""Flower adapters of a snapshot federation (``fedmap run --deploy``, ``fedmap base-station``): the
rover's ClientApp (``client``), the base station's ServerApp and strategy (``server``) and their
Flower App (``app/``).
"""
