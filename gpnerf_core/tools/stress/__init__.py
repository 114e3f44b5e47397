"""The stress suite: trained models evaluated under graded conditions (``runner``) and summarised (``summary``); driven
by ``python -m gpnerf_core stress``."""
