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


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, told in words: what was running when it came (`doing`, e.g. "reconstruct, in the
    normals stage") and what it left behind (`left`, e.g. "no partial result was left; out/ is
    unchanged"). Raised in place of the KeyboardInterrupt by the code that knows; the CLI prints
    it as one line and exits with status 130."""

    def __init__(self, doing: str = "", left: str = ""):
        super().__init__(doing)
        self.doing, self.left = doing, left

    def __str__(self) -> str:
        return "interrupted" + (f": {self.doing}" if self.doing else "") + (f"; {self.left}" if self.left else "")
