"""Exception hierarchy of fgslam.

Every error a user can cause (bad files, bad configuration, unusable data) is an ``FGSlamError``
whose message names the file, line or key at fault; the CLI turns these into one-line messages.
"""


class FGSlamError(Exception):
    """Base class of all errors fgslam raises on purpose."""


class ConfigError(FGSlamError):
    """Invalid configuration: unknown key, wrong type or value."""


class DataError(FGSlamError):
    """Missing, unreadable or inconsistent input data."""


class FormatError(DataError):
    """A file that does not follow its format (names the file and the line)."""


class EvaluationError(FGSlamError):
    """Trajectories that cannot be compared (no association, length mismatch...)."""


class OptimizationError(FGSlamError):
    """An optimisation problem that is ill-posed or failed."""


class Interrupted(KeyboardInterrupt):
    """A run stopped by a signal (SIGINT, SIGTERM) after writing its partial outputs.

    A ``KeyboardInterrupt`` (so that ``except Exception`` in library code never swallows it);
    ``exit_code`` is the shell's ``128 + signal number`` (130 for SIGINT, 143 for SIGTERM).
    """

    def __init__(self, message: str, signum: int) -> None:
        super().__init__(message)
        self.signum = signum
        self.exit_code = 128 + signum
