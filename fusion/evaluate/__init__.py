"""Evaluation against ground truth: metrics (pure maths), plots, Markdown report."""
