"""The ``mvsplat`` model family: MVSplat's feed-forward 3D Gaussians (cost volume, one Gaussian per source pixel),
rasterized, with semantics by label rendering or a head; ``model.py`` states what is faithful and what is simplified."""
