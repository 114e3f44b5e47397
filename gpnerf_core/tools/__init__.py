"""Measurement, reporting and viewing built on the engine: bench, stress, sizing, reporting and the web viewer."""
