"""``model=semantic_3dgs``: per-scene semantic 3D Gaussian splatting (docs/families/semantic_3dgs.md)."""
