"""Evaluation: metrics tagged by protocol id (``metrics``) and the pictures a run writes (``visualize``)."""
