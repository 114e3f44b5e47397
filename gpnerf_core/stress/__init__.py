"""The stress suite: trained models evaluated under graded conditions (``python -m gpnerf_core stress``)."""
