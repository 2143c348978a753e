"""One error type for everything a user can get wrong.

The CLI prints ``str(error)`` as a single line and exits with code 2; messages name the
file, key or value and what was expected.
"""


class ThermoGNNError(Exception):
    """A user-facing error: bad input file, unknown config key, mismatched checkpoint, ..."""


class ConfigError(ThermoGNNError):
    """An unknown or ill-typed configuration key or value."""


class DataError(ThermoGNNError):
    """A missing, corrupt or mismatched data file (dataset, checkpoint, exported model)."""


class DeviceError(ThermoGNNError):
    """A haptic device plugin that cannot be found, opened or driven."""
