"""User-facing errors: one line naming the file, key or value and what was expected."""


class GpnerfError(Exception):
    """An error caused by input (config, data, plugins); the CLI prints it on one line and exits 2."""


class ConfigError(GpnerfError):
    """A config key or value is invalid."""


class DataError(GpnerfError):
    """A dataset file is missing or malformed."""


class PluginError(GpnerfError):
    """A plugin is missing, duplicated or broken."""


class NonFiniteError(GpnerfError):
    """NaN or Inf reached a loss, a pose or a gradient."""
