"""Errors the tool raises on purpose. Each prints as one line at the CLI boundary."""

from __future__ import annotations

#: Exit codes, documented in the README: 0 done, 1 error, 2 usage (click's own, for an
#: unknown option or a malformed value; ``OptionValueError`` for a value out of range),
#: 3 waiting on results (``PendingResultsError``, and ``bams-cli status`` while picks await
#: results).
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_PENDING = 0, 1, 2, 3


def shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` for an error message, cut to ``limit`` characters: an id or a cell
    of 100,000 characters is named by its start and its length, not echoed whole."""
    text = repr(value)
    if len(text) <= limit:
        return text
    size = f" ({len(value)} characters)" if isinstance(value, str | bytes) else ""
    return f"{text[: limit - 3]}...{size}"


class BamsError(Exception):
    """Base class: a problem the user can fix; printed as one line, exit code 1."""

    exit_code: int = EXIT_ERROR


class InputError(BamsError):
    """An input file has a bad value; the message names the file, column and row."""

    def __init__(
        self, file: object, message: str, *, column: str | None = None, row: int | None = None
    ):
        where = str(file)
        if column is not None:
            where += f": column {shown(column)}"
        if row is not None:
            where += f", row {row}" if column is not None else f": row {row}"
        super().__init__(f"{where}: {message}")
        self.file, self.column, self.row = str(file), column, row


class SchemaError(InputError):
    """A table lacks a required column or has one of the wrong type."""


class DuplicateError(InputError):
    """A key that must be unique appears more than once."""


class ConflictError(BamsError):
    """New results disagree with results already in the observation log."""


class WorkspaceError(BamsError):
    """The workspace is missing, not initialised, or in a state the command cannot use."""


class WorkspaceLockedError(WorkspaceError):
    """Another command holds the workspace lock."""


class StaleStateError(WorkspaceError):
    """A derived state file (model, scores) is older than what it was derived from."""


class PendingResultsError(WorkspaceError):
    """Selected picks (a batch, an estimate plan) await results; exit code 3, not an error."""

    exit_code = EXIT_PENDING


class AbandonedRunsError(WorkspaceError):
    """Requests an answer needs were abandoned (``bams-cli abandon``); a flag says how to count them."""


class SettingsError(BamsError):
    """The settings file or a flag holds an invalid value."""

    def __init__(self, message: str, *, setting: str | None = None):
        super().__init__(message)
        #: The setting at fault (gammas, levels, seed, embedding_dim), when there is one:
        #: ``init`` names the flag that gave it.
        self.setting = setting


class OptionError(BamsError):
    """A command-line option out of range or unknown."""


class OptionValueError(OptionError):
    """An option's value is out of range whatever the workspace holds (``--budget -5``):
    a usage error, exit code 2, as click's own for a malformed value."""

    exit_code = EXIT_USAGE
