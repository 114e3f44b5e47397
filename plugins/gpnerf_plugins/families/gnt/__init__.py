"""The ``gnt`` model family: GNT's view and ray transformers with GP-NeRF's attention-reusing semantic field."""
