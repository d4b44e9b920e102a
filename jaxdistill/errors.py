"""Errors a user can cause, each naming the file and the field that is wrong."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input, reported with where it is (file, field) and what to do.

    `problems` is a list of `(file, field, message)`; all problems found by one
    validation pass are reported together, one per line.
    """

    def __init__(self, problems: list[tuple[str, str, str]]):
        self.problems = list(problems)
        lines = [f"{file}: {field}: {message}" for file, field, message in self.problems]
        head = "invalid input" if len(lines) == 1 else f"invalid input ({len(lines)} problems)"
        super().__init__(head + ":\n  " + "\n  ".join(lines))

    @classmethod
    def single(cls, file: str, field: str, message: str) -> "InputError":
        return cls([(str(file), field, message)])


class ProblemList:
    """Collects problems during validation; `raise_if_any()` raises them as one InputError."""

    def __init__(self):
        self.problems: list[tuple[str, str, str]] = []

    def add(self, file, field: str, message: str) -> None:
        self.problems.append((str(file), field, message))

    def raise_if_any(self) -> None:
        if self.problems:
            raise InputError(self.problems)

    def __bool__(self) -> bool:
        return bool(self.problems)
