"""Errors a user can cause, each naming the file and the field that is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


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


def read_json(path, missing: str) -> Any:
    """The parsed JSON file; InputError naming the file (and the line) when it is missing or
    invalid. `missing` says what to do when the file does not exist."""
    path = Path(path)
    if not path.is_file():
        raise InputError.single(path, "(file)", missing)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise InputError.single(path, f"line {err.lineno}", f"not valid JSON: {err.msg}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError.single(path, "(file)", f"not valid JSON: unreadable as UTF-8 text ({err})") from None


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
