"""Scoring a map against ground truth: image metrics, the path F1, and typed results."""
