"""Atomic, metadata-stamped writes and strict reads of workspace files.

Every write goes to a temporary file in the destination folder, is fsynced, and is then
renamed over the target, so a crash leaves either the old file or the new one, never half
of one. A command that writes several files stages them all in one ``Transaction`` and
renames them only after every step has succeeded: a failing command leaves the workspace
exactly as it was.
"""

from __future__ import annotations

import contextvars
import datetime as dt
import difflib
import hashlib
import json
import os
import shlex
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from bams_cli import __version__, memory
from bams_cli.errors import InputError, SchemaError, shown

META_PREFIX = "bams."


def command_line() -> str:
    """The command line of this process, as recorded in every file it writes."""
    argv = list(sys.argv)
    if argv:
        argv[0] = Path(argv[0]).name
    return shlex.join(argv)


def stamp(table: pa.Table, schema_version: int, extra: dict[str, Any] | None = None) -> pa.Table:
    """Attach the tool's key-value metadata (schema version, tool version, command, time)."""
    meta = dict(table.schema.metadata or {})
    fields = {
        "schema_version": str(schema_version),
        "tool_version": __version__,
        "command": command_line(),
        # To the microsecond: status orders a study's lists by it (a copied workspace's
        # modification times are the copy's), and a loop writes several in one second.
        "written_at": dt.datetime.now(dt.UTC).isoformat(timespec="microseconds"),
    }
    for key, value in (extra or {}).items():
        # allow_nan=False: metadata is JSON; an undefined number must be written as null.
        fields[key] = value if isinstance(value, str) else json.dumps(value, allow_nan=False)
    for key, value in fields.items():
        meta[(META_PREFIX + key).encode()] = str(value).encode()
    return table.replace_schema_metadata(meta)


@contextmanager
def _state_file(path: Path) -> Iterator[None]:
    """Turn a damaged workspace Parquet file into a one-line error naming it."""
    try:
        yield
    except FileNotFoundError:
        raise
    except (pa.ArrowException, OSError) as exc:
        first = " ".join(str(exc).split()) or type(exc).__name__
        raise SchemaError(path, f"damaged state file, not readable as Parquet ({first})") from None


def read_state(path: Path, columns: list[str] | None = None) -> pa.Table:
    """Read one of the workspace's own Parquet files; a damaged one is a one-line error."""
    with _state_file(path):
        return pq.read_table(path, columns=columns)


def read_state_schema(path: Path) -> pa.Schema:
    with _state_file(path):
        return pq.read_schema(path)


def read_metadata(path: Path) -> dict[str, str]:
    """The tool's metadata of a Parquet file, without the ``bams.`` prefix."""
    meta = read_state_schema(path).metadata or {}
    out = {}
    for key, value in meta.items():
        k = key.decode()
        if k.startswith(META_PREFIX):
            out[k[len(META_PREFIX) :]] = value.decode()
    return out


def read_metadata_json(path: Path) -> dict[str, Any]:
    """A state file's metadata with JSON values decoded (numbers, lists, dicts)."""
    out: dict[str, Any] = {}
    for key, value in read_metadata(path).items():
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    return out


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: The workspace a command holds the lock of: its transactions keep a journal there.
JOURNAL_NAME = ".bams-journal.json"
_journal: contextvars.ContextVar[Path | None] = contextvars.ContextVar("journal", default=None)


@contextmanager
def journal_in(workspace: Path) -> Iterator[None]:
    """Make transactions inside the block journal their renames in ``workspace``."""
    token = _journal.set(workspace / JOURNAL_NAME)
    try:
        yield
    finally:
        _journal.reset(token)


def recover(workspace: Path) -> int:
    """Finish or undo a commit that a crash interrupted; call it holding the lock.

    A commit renames its staged files one by one. If the process died among the renames,
    the journal it wrote first lists them all, and the staged files still waiting are
    renamed now (and the files it removes, removed): the commit completes (roll forward).
    Staged files with no journal belong to a transaction that never began to commit and
    are removed. Returns the number of files rolled forward.
    """
    path = workspace / JOURNAL_NAME
    moved = 0
    if path.exists():
        try:
            pairs = json.loads(path.read_text())["renames"]
        except (ValueError, KeyError, TypeError):
            pairs = []  # torn while being written: the commit had not started renaming
        folders = set()
        for tmp_name, target_name in pairs:
            target = _journalled(workspace, target_name)
            if tmp_name is None:  # a staged removal (``Transaction.remove``)
                if target.exists():
                    target.unlink()
                    folders.add(target.parent)
            elif (tmp := _journalled(workspace, tmp_name)).exists():
                os.replace(tmp, target)
                folders.add(target.parent)
                moved += 1
        for folder in folders:
            _fsync_dir(folder)
        path.unlink()
        _fsync_dir(workspace)
    for stray in workspace.rglob(".tmp-*"):
        if stray.is_file():
            stray.unlink()
    return moved


def recovered_note(workspace: Path, moved: int) -> str:
    """What a command says after ``recover`` completed an interrupted commit."""
    return (
        f"note: {workspace}: finished an interrupted command's commit ({moved} "
        f"file{'s' if moved != 1 else ''} renamed into place)\n"
    )


def _journal_name(workspace: Path, path: Path) -> str:
    """How the journal names ``path``: relative to the workspace when inside it, so a
    copied or moved workspace recovers its own files and never the original's; absolute
    otherwise (``select --out`` beside the workspace)."""
    # abspath, not resolve: a subfolder that is a symlink to other storage is still the
    # workspace's (a copy of the workspace recovers its own files there).
    path, root = Path(os.path.abspath(path)), Path(os.path.abspath(workspace))
    return path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path)


def _journalled(workspace: Path, name: str) -> Path:
    """The file a journal entry names (``_journal_name``); absolute entries as written."""
    return Path(name) if Path(name).is_absolute() else workspace / name


def remove_strays(target: Path) -> int:
    """Remove what a killed process staged for ``target`` outside a workspace (where
    ``recover`` does not look): ``.tmp-<name>-<pid>-*`` files of processes no longer
    alive. Call it after ``recover``, holding the workspace lock. Returns how many went."""
    removed = 0
    for stray in Path(target).parent.glob(f".tmp-{Path(target).name}-*"):
        pid = stray.name[len(f".tmp-{Path(target).name}-") :].split("-")[0]
        if not pid.isdigit() or _alive(int(pid)) or not stray.is_file():
            continue
        stray.unlink(missing_ok=True)
        removed += 1
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Transaction:
    """Stage files next to their targets; rename them all on commit, remove them on failure.

    Inside ``journal_in(workspace)`` (every command holding the workspace lock), a commit
    of more than one file first writes the list of renames to the workspace's journal, so
    a crash among the renames is completed by ``recover`` before the next command reads.
    """

    def __init__(self) -> None:
        # (staged file, target) in commit order; a staged file of None removes the target.
        self._staged: list[tuple[Path | None, Path]] = []
        self._made = 0

    def _temp_for(self, target: Path) -> Path:
        target.parent.mkdir(parents=True, exist_ok=True)
        self._made += 1
        return target.parent / f".tmp-{target.name}-{os.getpid()}-{self._made - 1}"

    def _finish(self, tmp: Path, target: Path) -> Path:
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        self._unstage(target)
        self._staged.append((tmp, target))
        return target

    def _unstage(self, target: Path) -> None:
        """Drop what is staged for ``target``: a later write (or removal) of the same file
        in one transaction replaces the earlier one (``ingest-results --abandon-failed``
        stages the pending lists twice, the second time knowing what was abandoned)."""
        for tmp, t in self._staged:
            if t == target and tmp is not None:
                tmp.unlink(missing_ok=True)
        self._staged = [(tmp, t) for tmp, t in self._staged if t != target]

    def staged(self, target: Path) -> bool:
        """Whether this transaction writes or removes ``target`` on commit."""
        return any(t == target for _, t in self._staged)

    def remove(self, target: Path) -> None:
        """Stage the removal of ``target``: on commit it goes with the renames (nothing if
        it is not there), and a commit killed before it is completed by ``recover``."""
        self._unstage(target)
        self._staged.append((None, target))

    def write_parquet(self, target: Path, table: pa.Table) -> Path:
        tmp = self._temp_for(target)
        pq.write_table(table, tmp, compression="zstd")
        return self._finish(tmp, target)

    def write_bytes(self, target: Path, data: bytes) -> Path:
        tmp = self._temp_for(target)
        tmp.write_bytes(data)
        return self._finish(tmp, target)

    def write_text(self, target: Path, text: str) -> Path:
        return self.write_bytes(target, text.encode())

    def write_with(self, target: Path, writer: Any) -> Path:
        """Stage a file produced by ``writer(tmp_path)`` (e.g. ``np.savez``, ``csv``)."""
        tmp = self._temp_for(target)
        writer(tmp)
        return self._finish(tmp, target)

    def commit(self) -> list[Path]:
        journal = _journal.get()
        if journal is not None and len(self._staged) > 1:
            ws = journal.parent
            pairs = [
                [None if tmp is None else _journal_name(ws, tmp), _journal_name(ws, target)]
                for tmp, target in self._staged
            ]
            staged = journal.parent / f".tmp-{journal.name}-{os.getpid()}"
            with open(staged, "w") as fh:
                json.dump({"renames": pairs}, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(staged, journal)
            _fsync_dir(journal.parent)
        folders = set()
        for tmp, target in self._staged:
            if tmp is None:
                target.unlink(missing_ok=True)
            else:
                os.replace(tmp, target)
            folders.add(target.parent)
        for folder in folders:
            _fsync_dir(folder)
        if journal is not None and len(self._staged) > 1:
            journal.unlink()
            _fsync_dir(journal.parent)
        done = [target for _, target in self._staged]
        self._staged.clear()
        return done

    def rollback(self) -> None:
        for tmp, _ in self._staged:
            if tmp is not None:
                tmp.unlink(missing_ok=True)
        self._staged.clear()


_open_tx: contextvars.ContextVar[Transaction | None] = contextvars.ContextVar(
    "open_transaction", default=None
)


@contextmanager
def transaction() -> Iterator[Transaction]:
    """``with transaction() as tx: tx.write_parquet(...)``: all files land, or none.

    A transaction opened inside another joins it: its files are staged in the outer one
    and land when that commits (``ingest-results --abandon-failed`` writes the observation
    log and the abandoned log as one commit).
    """
    outer = _open_tx.get()
    if outer is not None:
        yield outer
        return
    tx = Transaction()
    token = _open_tx.set(tx)
    try:
        yield tx
        memory.check()  # nothing lands once the command is over its --max-memory
    except BaseException:
        tx.rollback()
        raise
    finally:
        _open_tx.reset(token)
    tx.commit()


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_table(path: Path, *, what: str = "table") -> pa.Table:
    """Read a Parquet or CSV file the user handed over; unreadable -> one-line InputError."""
    if not path.exists():
        raise InputError(path, f"{what} file not found")
    if path.is_dir():
        raise InputError(path, f"is a folder; give the {what} file itself")
    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            import pyarrow.csv as pacsv

            # Ids stay text: type inference would turn "029" into 29; an empty status
            # column is still text.
            text = {name: pa.string() for name in ("segment_id", "request_id", "status")}
            # Only an empty field is missing: pyarrow's default also reads "nan", "NA" and
            # "NULL" as missing, and an error about a cell holding "nan" then said "got
            # nothing" (a Parquet file's NaN said "got nan").
            convert = pacsv.ConvertOptions(
                column_types=text, null_values=[""], strings_can_be_null=True
            )
            # One thread: only then does pyarrow number a ragged row (the handler keeps it).
            ragged: list[Any] = []

            def keep(row: Any) -> str:
                ragged.append(row)
                return "error"

            parse = pacsv.ParseOptions(invalid_row_handler=keep)
            try:
                table = pacsv.read_csv(
                    path,
                    read_options=pacsv.ReadOptions(use_threads=False),
                    parse_options=parse,
                    convert_options=convert,
                )
            except pa.ArrowInvalid:
                if ragged and ragged[0].number is not None:
                    bad = ragged[0]
                    fix = (
                        "quote fields that hold commas"
                        if bad.actual_columns > bad.expected_columns
                        else "give every column a field, empty ones as ,,"
                    )
                    raise InputError(
                        path,
                        f"has {bad.actual_columns} fields, the header {bad.expected_columns} "
                        f"({shown(bad.text)}); {fix}",
                        row=bad.number - 1,  # counted with the header as row 1
                    ) from None
                raise
        else:
            table = pq.read_table(path)
    except (pa.ArrowException, OSError, UnicodeDecodeError) as exc:
        kind = "CSV" if suffix == ".csv" else "Parquet"
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(path, f"cannot read as {kind} ({first})") from None
    try:
        names = table.column_names
    except UnicodeDecodeError:
        raise InputError(path, "the header is not valid UTF-8 text") from None
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise InputError(path, "column appears more than once in the header", column=name)
        seen.add(name)
    return table


def require_columns(table: pa.Table, columns: list[str], source: object) -> None:
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise SchemaError(
            source,
            f"missing required column(s) {', '.join(map(repr, missing))}; "
            f"found {', '.join(map(repr, table.column_names))}"
            + near_misses(missing, table.column_names),
            column=missing[0],
        )


def _plain(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


def near_miss(want: str, found: list[str], taken: Sequence[str] = ()) -> str | None:
    """The column of ``found`` that spells ``want`` another way (case, spaces, dashes, or
    a close misspelling), if one does; ``taken`` names are never offered."""
    # A number at the end names another thing (value_1 is level 1's value, not "value";
    # value_2 is not value_0): never offered across one.
    other = [
        f
        for f in found
        if f != want and f not in taken and _number_at_end(f) == _number_at_end(want)
    ]
    like = [f for f in other if _plain(f) == _plain(want)]
    like = like or difflib.get_close_matches(want, other, n=1, cutoff=0.75)
    return like[0] if like else None


def _number_at_end(name: str) -> str:
    plain = _plain(name)
    return plain[len(plain.rstrip("0123456789")) :]


def near_misses(wanted: list[str], found: list[str]) -> str:
    """ "; rename 'Value' to 'value'" for each wanted column the file spells another way,
    or "" when none looks like one."""
    pairs = [
        f"{like!r} to {want!r}"
        for want in wanted
        if (like := near_miss(want, found, wanted)) is not None
    ]
    return f"; rename {', '.join(pairs)} (column names are exact)" if pairs else ""


def is_id_type(t: pa.DataType) -> bool:
    """Whether an id column of this Arrow type reads as one text id per row: text,
    integers (their decimal text), all-null, or dictionary-encoded text (pandas categories)."""
    if pa.types.is_dictionary(t):
        t = t.value_type
    return (
        pa.types.is_string(t)
        or pa.types.is_large_string(t)
        or pa.types.is_integer(t)
        or pa.types.is_null(t)
    )


def first_valid(values: pa.ChunkedArray | pa.Array) -> tuple[int, Any]:
    """(row counted from 1, value) of a column's first non-null entry; (1, None) if none."""
    valid = values.is_valid().to_numpy(zero_copy_only=False)
    if not valid.any():
        return 1, None
    row = int(valid.argmax())
    return row + 1, values[row].as_py()


def require_id_column(
    table: pa.Table,
    column: str,
    source: object,
    what: str,
    expected: str = "text or an integer, one id per row",
) -> None:
    """A SchemaError naming the first row of an id column that holds a list, a struct,
    bytes, a float ... instead of one text id (or integer) per row."""
    if column not in table.column_names:
        return
    t = table.schema.field(column).type
    if is_id_type(t):
        return
    row, value = first_valid(table.column(column))
    raise SchemaError(
        source, f"{what} {shown(value)} is of type {t}; expected {expected}", column=column, row=row
    )
