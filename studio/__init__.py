"""Synthetic capture studio (``python -m studio``): complete two-person sessions in the real
input formats, with exact ground truth kept apart in ``<out>/gt/``."""
