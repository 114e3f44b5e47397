"""Replica: the ``replica`` and ``replica_instance`` datasets, their layout readers, checkers, classes and splits."""
