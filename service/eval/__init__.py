"""Evaluation against labelled data: the paper's ground-truth comparison, baselines and figures."""
