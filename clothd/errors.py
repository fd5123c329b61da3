"""clothd's exceptions. The API maps them to HTTP codes; the CLI prints them without a traceback."""


class ClothdError(Exception):
    """Base of every error clothd raises on purpose."""


class ConfigError(ClothdError):
    """A configuration that cannot be used; the message names the key and the bound."""


class InputError(ClothdError):
    """Input footage or a recording that cannot be read, with what is wrong with it."""


class TrackingLostError(ClothdError):
    """The cloth cannot be found or the filter diverged; tracking must re-initialise."""
