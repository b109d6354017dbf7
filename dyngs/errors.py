"""Errors a user can fix. The CLI reports these as one line (no stack trace); anything
else is a bug and keeps its traceback."""


class UserError(Exception):
    """Bad input or an impossible request; the message names the culprit and the fix."""


class ConfigError(UserError):
    """A config value that cannot work (negative iterations, unknown split, …)."""


class DatasetError(UserError, ValueError):
    """Bad input data. The message is one line naming the file and the problem."""


class RendererUnavailable(UserError, RuntimeError):
    """The chosen renderer cannot run on this machine (the message says what is missing)."""
