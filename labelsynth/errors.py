"""Errors that the CLI turns into a one-line message and a non-zero exit code."""


class LabelsynthError(Exception):
    """Base class: anything the user can fix (bad input, bad option, existing output)."""


class CaptureError(LabelsynthError, ValueError):
    """Bad input in a capture folder. The message is one line that names the file."""


class ClassMapError(CaptureError):
    """A classes.json or labelmap.txt that cannot be used."""


class RecipeError(LabelsynthError, ValueError):
    """A recipe that does not exist or has unknown or ill-typed keys."""


class CheckError(CaptureError):
    """Every bad input of a run found at once (``capture.check``), one line per file in
    ``problems``, so that a user fixes them all before the next try rather than one per run."""

    def __init__(self, problems: list[str], summary: str) -> None:
        self.problems = list(problems)
        self.summary = summary
        text = self.problems[0] if len(self.problems) == 1 else "\n".join([summary, *self.problems])
        super().__init__(text)
