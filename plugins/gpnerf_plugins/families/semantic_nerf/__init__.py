"""Semantic-NeRF (Zhi et al., ICCV 2021) as a per-scene model family: ``model=semantic_nerf``."""
