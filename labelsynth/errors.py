"""Errors that the CLI turns into a one-line message and a non-zero exit code."""


class LabelsynthError(Exception):
    """Base class: anything the user can fix (bad input, bad option, existing output)."""


class CaptureError(LabelsynthError, ValueError):
    """Bad input in a capture folder. The message is one line that names the file."""


class ClassMapError(CaptureError):
    """A classes.json or labelmap.txt that cannot be used."""


class RecipeError(LabelsynthError, ValueError):
    """A recipe that does not exist or has unknown or ill-typed keys."""
