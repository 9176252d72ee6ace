"""Typed errors. Every error a user can cause derives from `E3DPSMError`; the CLI turns it
into one line on stderr and a non-zero exit, never a traceback."""


class E3DPSMError(Exception):
    """Base class of the errors caused by bad input or configuration."""


class ConfigError(E3DPSMError, ValueError):
    """An unknown variant, an invalid option, or a config that does not fit."""


class InputError(E3DPSMError, ValueError):
    """A tensor, array, event stream or state of the wrong shape, dtype or content."""


class DataError(E3DPSMError):
    """A missing, truncated, corrupted or unsafe file or data folder."""


class CheckpointError(DataError):
    """A checkpoint that cannot be loaded or does not match what was asked for."""


class OutputExistsError(E3DPSMError, FileExistsError):
    """An output that already exists and would be overwritten without --force."""
