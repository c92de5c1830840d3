"""Every exception and warning pbrdf-cl raises, in one place (all exported as ``pbrdf_cl.<Name>``).

Errors name the offending field, value, index or line in one line; the command line prints that
line alone (``pbrdf-cl: error: ...``).  Most input errors are plain ``ValueError``\\ s; the
classes here mark what a caller may want to tell apart.
"""


# ---- the device

class OpenCLUnavailableError(RuntimeError):
    """No usable OpenCL platform or device."""


class DeviceUnusableError(OpenCLUnavailableError):
    """An explicitly chosen OpenCL device cannot build or run pbrdf-cl's kernels."""


class KernelBuildError(OpenCLUnavailableError):
    """A driver failed to build one of pbrdf-cl's programs (the first line of its log says why)."""


class ProgramUnusableError(KernelBuildError):
    """A device cannot run one program: its trial build in a child process failed, crashed, aborted
    or timed out (``pbrdf_cl.device.trials``).

    Parameters
    ----------
    message : str
        The one-line message.
    engine : pbrdf_cl.Engine, optional
        Where.
    verdict : dict, optional
        The trial's finding.
    program : tuple, optional
        A key of the program that does not depend on the device.
    """

    def __init__(self, message, engine=None, verdict=None, program=None):
        super().__init__(message)
        self.engine = engine
        self.verdict = verdict
        self.program = program


class TrialError(RuntimeError):
    """The trial machinery itself failed (the child process could not be started)."""


class DeviceWarning(UserWarning):
    """An OpenCL device was skipped, or the computation fell back to another device or to the numpy
    backend."""


# ---- the inputs

class UnitsWarning(UserWarning):
    """Inputs that look like a unit or convention mistake (angles in radians, DOP in percent, ...)."""


class DataWarning(UserWarning):
    """Part of the measurements was ignored (columns that are not inputs of the model); the
    message names what and where."""


class RangeError(ValueError):
    """A value, range, bounds or ``name=value`` text that the grammar refuses; the message is one
    line naming where it was given, the text, the reason and the right spelling."""


class SpecError(ValueError):
    """A sweep spec (or the store it is resumed into) is not valid; the message names the field."""


class TooLargeError(MemoryError, ValueError):
    """An output that cannot fit, found before any work (a ``MemoryError`` and a ``ValueError``,
    so that both ``except`` clauses a caller may have catch it)."""


class StoreError(ValueError):
    """A store cannot take this job (another job's store, other settings, another input, other
    kernels); the message names what differs."""


class StoreWarning(UserWarning):
    """A store was repaired or taken over while resuming (damaged chunks recomputed, metadata
    rewritten from the spec, a dead run's lock taken over, another device): one line naming it."""


class CommandError(Exception):
    """A command refused before any work (an option, an output that cannot be written, an
    environment problem): the message is the whole report."""


# ---- the results

class SensitivityWarning(UserWarning):
    """Settings whose indices cannot mean what they seem (ks and kd both ranged for the DOP)."""
