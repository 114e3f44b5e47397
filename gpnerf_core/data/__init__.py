"""Data a model is trained and evaluated on: scenes and frames loaded and cached, the checks of a dataset's files."""
