"""The ``mvsnerf`` model family: MVSNeRF's cost volume and modulated MLP with a semantic head (GP-NeRF Table 1's
"MVSNeRF + Semantic Head"); ``model.py`` states what is faithful and what is simplified."""
