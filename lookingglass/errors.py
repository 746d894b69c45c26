"""The one exception type the command line turns into a clear message and a non-zero exit."""


class LookingGlassError(Exception):
    """A problem with the user's input or request, stated so the user can fix it.

    The message names the file (when there is one) and the problem; the CLI prints it without
    a traceback and exits with status 2.
    """

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class LookingGlassWarning(UserWarning):
    """Something odd but usable in the user's input (an unknown key, a duplicated camera...).

    Emitted with `warnings.warn(LookingGlassWarning(message))`; the message names the file and
    the oddity, like LookingGlassError's.
    """


class ConfigError(LookingGlassError, ValueError):
    """A configuration value out of its range: raised by the config dataclasses' own checks, so a
    flag, a preset and a loaded config JSON are all refused the same way (one line at the CLI)."""
