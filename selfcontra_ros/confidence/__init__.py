"""Confidence measures, their feature sets, and the random forest trained on labels (DESIGN section 5)."""
