"""Configuration: the primary config's schema, its composition, override strings and the argument parser of the commands
that are not Hydra jobs."""
