"""Built-in depth sources (``+depth_source=cost_volume|source_depth``) for ``model.sampler=depth``."""
