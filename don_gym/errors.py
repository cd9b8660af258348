"""Exceptions for errors a user can cause.

Every error that comes from user input (a bad mesh, a bad path, a NaN action, a
checkpoint for another object) is a :class:`DonGymError`. It subclasses
``ValueError`` so that generic code catching ``ValueError`` keeps working, and the
``don-gym`` CLI prints it as one line and exits non-zero instead of a traceback.
"""

from __future__ import annotations


class DonGymError(ValueError):
    """A problem with user input; the message names the input and what was expected."""


class MeshError(DonGymError):
    """A mesh file or mesh array that cannot be used as an object model."""


class CheckpointError(DonGymError):
    """A checkpoint that is unreadable or does not match what the caller needs."""


class DatasetError(DonGymError):
    """A dataset directory that is missing, corrupt, or holds a different dataset."""


class SeveralPiecesError(MeshError):
    """A mesh in several connected pieces where one is needed. ``detail`` says so without advice, for
    callers that give their own (what to pass depends on the caller: a keyword, a CLI option)."""

    def __init__(self, detail: str, advice: str = "") -> None:
        super().__init__(f"{detail}. {advice}" if advice else detail)
        self.detail, self.advice = detail, advice

    def __reduce__(self) -> tuple[type, tuple[str, str]]:  # picklable from worker processes
        return type(self), (self.detail, self.advice)
