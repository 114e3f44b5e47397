"""The interactive web viewer of ``python -m gpnerf_core view``: a viser scene of a dataset's cameras and depth points,
and the model's novel view for each browser's camera, rendered progressively in a background thread.

``camera``: viser's camera <-> the framework's OpenCV pose and intrinsics (pure functions).
``renderer``: one view rendered with ``GeneralizableNeRF.predict`` and turned into picture layers
(``SceneRenderer``), and the progressive, cancellable, per-client render thread (``ProgressiveRenderer``).
``server``: the viser server, its scene content and GUI (``ViewerServer``).
"""
