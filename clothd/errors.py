"""clothd's exceptions. The CLI prints them without a traceback (and the API will map them to HTTP codes)."""


class ClothdError(Exception):
    """Base of every error clothd raises on purpose."""


class ConfigError(ClothdError):
    """A configuration that cannot be used; the message names the key and the bound."""


class InputError(ClothdError):
    """Input footage or a recording that cannot be read, with what is wrong with it."""


class HardwareError(ClothdError):
    """The camera or the stepper controller is missing, silent or answering nonsense."""


class RequestError(ClothdError):
    """An API request that cannot be carried out in the daemon's current state (HTTP 409)."""


class InvalidRequestError(RequestError):
    """A request that can never be carried out as given, whatever the state (HTTP 422)."""


class UnreachableTargetError(InvalidRequestError):
    """A setpoint whose target the cloth cannot reach, such as one off the workspace (HTTP 422)."""


class StorageError(RequestError):
    """Somewhere the daemon was asked to write, and cannot (HTTP 507)."""
