"""Errors a user can fix. The entry point prints them as one paragraph, without a traceback."""


class PipelineError(Exception):
    """A problem with the input (config, files, arguments), explained in the message."""


class ConfigError(PipelineError):
    """A config value that is not allowed. The message names the key, the value and what is allowed."""
