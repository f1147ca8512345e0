"""``bams-cli init``: create a workspace and its settings, under the lock."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

from bams_cli.errors import (
    InputError,
    OptionError,
    OptionValueError,
    SettingsError,
    WorkspaceError,
)
from bams_cli.settings import Settings, levels_from_costs
from bams_cli.state.io import (
    transaction,
)
from bams_cli.state.lock import workspace_lock
from bams_cli.state.workspace import Workspace


# ---------------------------------------------------------------------------------------
# init
# ---------------------------------------------------------------------------------------
def init(
    root: Path,
    *,
    gammas: list[float] | None = None,
    costs: list[float] | None = None,
    level_names: list[str] | None = None,
    seed: int | None = None,
    dim: int | Literal["auto"] | None = None,
    settings_from: Path | None = None,
    force: bool = False,
    exist_ok: bool = False,
    wait: bool = False,
) -> dict[str, Any]:
    """Create a workspace and its settings file (flags > --settings-from file > defaults).

    A failure threshold is required: ``gammas`` or a ``settings_from`` file. The settings
    are built (and checked) first, so bad flags create nothing; whether the workspace
    exists is checked holding the lock, so of two concurrent inits one creates it and the
    other finds it there. With ``exist_ok`` an existing settings file holding exactly the
    requested settings is kept (``unchanged`` in the summary); one holding others is an
    error naming the differences.

    Parameters
    ----------
    root : Path
        The workspace folder to create (``--workspace``/``-w``).
    gammas : list of float, optional
        Failure thresholds on the metric f (``--gamma``); required unless
        ``settings_from`` gives them.
    costs : list of float, optional
        Cost per fidelity level, level 0 first (must be 1) (``--costs``).
    level_names : list of str, optional
        Names for the levels, one per level (``--level-names``).
    seed : int, optional
        Seed recorded and used by every step (``--seed``).
    dim : int or "auto", optional
        Reduced embedding dimension (``--dim``).
    settings_from : Path, optional
        Start from this settings.toml; the other arguments override it.
    force : bool, default False
        Overwrite an existing settings.toml.
    exist_ok : bool, default False
        Succeed without writing when settings.toml already holds these settings.
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``workspace``, ``settings`` (the file), ``gammas``,
        ``levels`` (``name``, ``cost`` each), ``seed``, ``embedding_dim``; ``unchanged``
        when ``exist_ok`` kept the file, else ``warnings`` (a cheap level that costs as
        much as level 0 or more).

    Raises
    ------
    OptionValueError
        An argument holds an invalid value (a repeated gamma, a level-0 cost other than 1,
        a cost not > 0, a negative seed ...), named by its flag; exit code 2.
    SettingsError
        A setting in ``settings_from`` is invalid.
    OptionError
        No threshold is given, or both ``force`` and ``exist_ok``.
    WorkspaceError
        The workspace exists already (without ``force``), or holds other settings
        (with ``exist_ok``).
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    if force and exist_ok:
        raise OptionError(
            "init: --force overwrites settings.toml and --exist-ok keeps it; pass one of them"
        )
    if not gammas and settings_from is None:
        raise OptionError(
            "init: no failure threshold given; pass --gamma (e.g. --gamma 0.5, comma-separated "
            "for several) or --settings-from FILE"
        )
    if Path(root).exists() and not Path(root).is_dir():
        raise WorkspaceError(f"{root}: is a file; a workspace is a folder, choose another -w")
    ws = Workspace(root)
    base = Settings()
    if settings_from is not None:
        if not settings_from.exists():
            raise InputError(settings_from, "settings file not found")
        base = Settings.from_file(settings_from)
    levels = levels_from_costs(costs, level_names) if costs else None
    if level_names and not costs:
        # Names for the levels the study has already (the settings file's, or level 0 alone).
        have = base.levels
        if len(level_names) != len(have):
            raise OptionValueError(
                f"--level-names has {len(level_names)} names for the study's {len(have)} "
                f"level{'s' if len(have) > 1 else ''}"
                + (" (level 0 alone)" if len(have) == 1 else "")
                + "; pass --costs to set the levels"
            )
        levels = levels_from_costs([lv.cost for lv in have], level_names)
    try:
        settings = base.with_overrides(
            gammas=tuple(gammas) if gammas else None, levels=levels, seed=seed, embedding_dim=dim
        )
    except SettingsError as exc:
        # The base was checked when it was read, so a flag holds the bad value: a usage
        # error naming the flag and its values.
        flags = {
            "gammas": ("--gamma", gammas),
            "levels": ("--costs", costs),
            "level_names": ("--level-names", level_names),
            "seed": ("--seed", seed),
            "embedding_dim": ("--dim", dim),
        }
        flag, value = flags.get(exc.setting or "", ("", None))
        if value is None:
            raise
        typed = (
            ",".join(v if isinstance(v, str) else f"{v:g}" for v in value)
            if isinstance(value, list)
            else value
        )
        raise OptionValueError(f"{flag} {typed}: {str(exc).removeprefix('settings: ')}") from None
    with workspace_lock(root, wait=wait), transaction() as tx:
        if ws.settings_path.exists() and exist_ok:
            existing = Settings.from_file(ws.settings_path)
            if dim is None and settings_from is None:
                # The default changed (12 -> "auto", 2026-11-25): a re-run of the init that
                # made an older workspace, without --dim, asks for nothing different.
                settings = replace(settings, embedding_dim=existing.embedding_dim)
            differences = _settings_differences(existing, settings)
            if differences:
                raise SettingsError(
                    f"{ws.settings_path}: already exists with other settings "
                    f"({'; '.join(differences)}); pass the same flags as before, or --force "
                    "to overwrite it"
                )
            return {
                "workspace": str(root),
                "settings": str(ws.settings_path),
                "unchanged": True,
                **settings_summary(settings),
            }
        if ws.settings_path.exists() and not force:
            raise WorkspaceError(
                f"{ws.settings_path}: already exists; edit it, pass --force to overwrite it, "
                "or --exist-ok to keep it when it holds these settings"
            )
        tx.write_text(ws.settings_path, settings.to_toml())
    source = "--costs " + ",".join(f"{c:g}" for c in costs) if costs else str(settings_from)
    return {
        "workspace": str(root),
        "settings": str(ws.settings_path),
        **settings_summary(settings),
        "warnings": settings.dear_levels(source),
    }


def _settings_differences(existing: Settings, requested: Settings) -> list[str]:
    """Each setting that differs, as "name: X in the file, Y requested"."""

    def levels(s: Settings) -> str:
        return ", ".join(f"{lv.name} {lv.cost:g}" for lv in s.levels)

    shown = {
        "gammas": lambda s: ", ".join(f"{g:g}" for g in s.gammas),
        "levels (costs)": levels,
        "seed": lambda s: str(s.seed),
        "embedding_dim": lambda s: str(s.embedding_dim),
        "id_column": lambda s: s.id_column,
        "extra": lambda s: json.dumps(s.extra, sort_keys=True),
    }
    return [
        f"{name}: {show(existing)} in the file, {show(requested)} requested"
        for name, show in shown.items()
        if show(existing) != show(requested)
    ]


def settings_summary(s: Settings) -> dict[str, Any]:
    return {
        "gammas": list(s.gammas),
        "levels": [{"name": lv.name, "cost": lv.cost} for lv in s.levels],
        "seed": s.seed,
        "embedding_dim": s.embedding_dim,
    }
