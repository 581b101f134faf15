"""Federated aggregation (one module of math) and the in-process runner."""
