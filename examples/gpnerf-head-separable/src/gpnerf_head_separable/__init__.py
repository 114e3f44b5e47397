"""Example gpnerf-core plugin: the ``separable`` head and the ``dice`` loss set (registered in ``plugin``)."""

__version__ = "0.1.0"
