"""Features of any 2D model in 3D (issue 57): feature providers and their on-disk cache, and queries against a
rendered feature map or a per-Gaussian / per-point feature matrix (``queries``)."""
