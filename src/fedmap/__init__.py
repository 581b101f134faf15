"""fedmap: federated multi-agent mapping for planetary exploration."""

__version__ = "0.1.0"
