"""Evaluation against ground truth: label metrics, plots."""
