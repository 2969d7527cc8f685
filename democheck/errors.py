"""democheck's own error types.

Anything a user can cause (a bad path, a broken file, a wrong option) raises a
``DemocheckError`` whose message is one line naming the file and the problem;
the CLI prints it and exits with status 2, without a traceback.
"""


class DemocheckError(Exception):
    """A problem with the user's input, reported as one line: a line break in it (a file name or a value from
    the user's metadata can hold one) is shown as ``\\n``."""

    def __str__(self) -> str:
        return super().__str__().replace("\r", "\\r").replace("\n", "\\n")


class DatasetError(DemocheckError):
    """A dataset that cannot be read: missing files, malformed metadata, wrong shapes."""


class RecipeError(DemocheckError):
    """A suite or training recipe that does not exist, does not parse, or names an unknown key."""
