"""Flower adapters of the map predictor's federation across sites (``fedmap federate-predictor
--deploy``): a site's ClientApp (``client``), the ServerApp (``server``), their run config
(``task``), the launcher (``deploy``) and their Flower App (``app/``).
"""
