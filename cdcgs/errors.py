"""The one exception cdcgs raises for bad user input read from files and folders."""

import os


class InputError(ValueError):
    """A file or folder given to cdcgs is missing, unreadable or malformed.

    Attributes:
        path: the file or folder at fault. problem: what is wrong with it.
    """

    def __init__(self, path, problem: str):
        self.path = os.fspath(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
