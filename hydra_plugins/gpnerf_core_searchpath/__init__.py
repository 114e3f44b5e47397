"""gpnerf-core's Hydra search-path plugin (``searchpath``): the config folders gpnerf plugins ship."""
