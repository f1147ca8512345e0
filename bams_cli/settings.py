"""Study settings: gammas, fidelity levels and costs, seed, embedding dimension.

Precedence, stated once: a command-line flag beats the workspace's ``settings.toml``,
which beats the defaults below. Only ``bams-cli init`` (and flags given to it) writes the
settings file; other commands read it and may override a value for one run.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import tomli_w

from bams_cli.errors import OptionValueError, SettingsError

SETTINGS_FILE = "settings.toml"

HEADER = """\
# bams-cli study settings. Edit by hand or with `bams-cli init --force`.
# gammas: failure thresholds (a segment fails when its metric f <= gamma); the first one
#         drives selection, every one is scored and estimated.
# levels: fidelity levels, level 0 = the high-fidelity simulator with cost 1; cheaper
#         simulators follow with their cost in units of one level-0 run.
"""


def _as_level_number(name: str) -> int | None:
    """The level number a results file's fidelity text ``name`` would read as, had no
    level that name (``state.handoff``: "1", "1.0", "1e0" are all level 1); None if none."""
    try:
        number = float(name)
    except ValueError:
        return None
    return int(number) if math.isfinite(number) and number == round(number) else None


#: The keys settings.toml may hold; anything else is a slip that would be ignored.
_TOP_KEYS = ("study", "levels", "extra")
_STUDY_KEYS = ("gammas", "seed", "embedding_dim", "id_column")
_LEVEL_KEYS = ("name", "cost")


def _known_keys(source: str, doc: dict[str, Any], study: dict[str, Any]) -> None:
    """Refuse a key settings.toml does not define (a misspelt ``seed`` would leave the seed
    at its default without a word), and an integer setting given as another type."""
    import difflib

    def refuse(key: str, where: str, known: tuple[str, ...]) -> None:
        near = difflib.get_close_matches(key, known, n=1)
        hint = f"did you mean {near[0]!r}? " if near else ""
        raise SettingsError(
            f"{source}: unknown key {key!r} in {where}; {hint}known keys: {', '.join(known)}"
        )

    for key in doc:
        if key not in _TOP_KEYS:
            refuse(key, "the file", _TOP_KEYS)
    for key in study:
        if key not in _STUDY_KEYS:
            refuse(key, "[study]", _STUDY_KEYS)
    levels = doc.get("levels", [])
    for i, lv in enumerate(levels):
        if not isinstance(lv, dict):
            raise SettingsError(f"{source}: levels entry {i} must be a {{name, cost}} table")
        for key in lv:
            if key not in _LEVEL_KEYS:
                refuse(key, f"levels entry {i}", _LEVEL_KEYS)
    for key in ("seed", "embedding_dim"):
        value = study.get(key)
        if key == "embedding_dim" and value == "auto":
            continue
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            also = ' or "auto"' if key == "embedding_dim" else ""
            raise SettingsError(
                f"{source}: {key} must be a whole number{also}, got {value!r}", setting=key
            )

    def number(value: Any) -> bool:
        return isinstance(value, int | float) and not isinstance(value, bool)

    # Every other value's type, by its key (a cost of "cheap" was "malformed entry (could
    # not convert string to float: 'cheap')", naming no key).
    for i, lv in enumerate(levels):
        for key in _LEVEL_KEYS:
            if key not in lv:
                raise SettingsError(f"{source}: levels entry {i} has no {key!r}", setting="levels")
        if not number(lv["cost"]):
            raise SettingsError(
                f"{source}: levels entry {i} ({lv['name']!r}): cost must be a number, got "
                f"{lv['cost']!r}",
                setting="levels",
            )
    gammas = study.get("gammas", [])
    if not isinstance(gammas, list) or not all(number(g) for g in gammas):
        raise SettingsError(
            f"{source}: gammas must be a list of numbers, got {gammas!r}", setting="gammas"
        )
    if not isinstance(study.get("id_column", ""), str):
        raise SettingsError(
            f"{source}: id_column must be a column name, got {study['id_column']!r}"
        )


@dataclass(frozen=True)
class Level:
    """One fidelity level: a simulator and what one run of it costs."""

    name: str
    cost: float


def _dim(value: Any) -> int | Literal["auto"]:
    return "auto" if value == "auto" else int(value)


@dataclass(frozen=True)
class Settings:
    """The study's settings, as written in ``settings.toml``."""

    gammas: tuple[float, ...] = (0.0,)
    levels: tuple[Level, ...] = (Level("high", 1.0),)
    seed: int = 0
    #: embed-reduce's default --dim: a number, or "auto" (from the embedding's spectrum,
    #: ``core.reduce.choose_dim``; the default since 2026-11-25, when 12 was).
    embedding_dim: int | Literal["auto"] = "auto"
    id_column: str = "segment_id"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def costs(self) -> tuple[float, ...]:
        return tuple(level.cost for level in self.levels)

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    def validate(self) -> Settings:
        if not self.gammas:
            raise SettingsError(
                "settings: gammas is empty; give at least one with --gamma", setting="gammas"
            )
        if any(not math.isfinite(g) for g in self.gammas):
            raise SettingsError(
                f"settings: gammas must be finite numbers, got {list(self.gammas)}",
                setting="gammas",
            )
        # Their order is kept (the first drives selection); a repeat is a slip, and would
        # score, estimate and report the same threshold twice.
        repeated = next((g for i, g in enumerate(self.gammas) if g in self.gammas[:i]), None)
        if repeated is not None:
            raise SettingsError(
                f"settings: gamma {repeated:g} is given more than once; give each failure "
                "threshold once",
                setting="gammas",
            )
        if not self.levels:
            raise SettingsError(
                "settings: no fidelity levels; give costs with --costs 1,0.1", setting="levels"
            )
        if self.levels[0].cost != 1.0:
            raise SettingsError(
                f"settings: level 0 must cost 1 (costs are in units of one level-0 run), "
                f"got {self.levels[0].cost:g}",
                setting="levels",
            )
        for i, level in enumerate(self.levels):
            if not (math.isfinite(level.cost) and level.cost > 0):
                raise SettingsError(
                    f"settings: level {i} cost must be a finite number > 0, got {level.cost:g}",
                    setting="levels",
                )
            # Results name their level by number or by name: a name must pick out one level.
            name = level.name.strip()
            if not name:
                raise SettingsError(f"settings: level {i} has an empty name", setting="level_names")
            if name in (other.name.strip() for other in self.levels[:i]):
                raise SettingsError(
                    f"settings: level name {name!r} is given to more than one level; results "
                    "that name their level would land at the wrong one: give each level its "
                    "own name",
                    setting="level_names",
                )
            if _as_level_number(name) not in (None, i):
                raise SettingsError(
                    f"settings: level {i} is named {name!r}, the number of another level; "
                    "results that name their level would land at the wrong one",
                    setting="level_names",
                )
        if self.seed < 0:
            raise SettingsError(
                f"settings: seed must be an integer >= 0, got {self.seed}", setting="seed"
            )
        if isinstance(self.embedding_dim, str) and self.embedding_dim != "auto":
            raise SettingsError(
                f'settings: embedding_dim must be a whole number or "auto", got '
                f"{self.embedding_dim!r}",
                setting="embedding_dim",
            )
        if self.embedding_dim != "auto" and self.embedding_dim < 1:
            raise SettingsError(
                f'settings: embedding_dim must be >= 1 or "auto", got {self.embedding_dim}',
                setting="embedding_dim",
            )
        return self

    def dear_levels(self, source: str) -> list[str]:
        """One warning per cheap level that costs as much as a level-0 run or more.

        Legal, and nothing breaks, but almost surely a slip (1,1.5 for 1,0.15, or costs not
        in units of one level-0 run): select scores a candidate by the variance of the
        level-0 metric it removes per unit cost, and a cheap run, carrying its level's
        discrepancy, removes less than a level-0 run of the same segment, so at the same
        cost or more the greedy all but never picks it, while a random mixed-fidelity batch
        still spends its share of the budget on it. ``source`` names the settings.
        """
        return [
            f"{source}: level {i} ({level.name}) costs {level.cost:g}, no less than a level-0 "
            "run (costs are in units of one level-0 run; a cheaper simulator costs a fraction "
            "of 1): select will seldom pick it, while random mixed-fidelity batches spend "
            "budget on it"
            for i, level in enumerate(self.levels)
            if i and level.cost >= 1
        ]

    def to_toml(self) -> str:
        doc: dict[str, Any] = {
            "study": {
                "gammas": list(self.gammas),
                "seed": self.seed,
                "embedding_dim": self.embedding_dim,
                "id_column": self.id_column,
            },
            "levels": [asdict(level) for level in self.levels],
        }
        if self.extra:
            doc["extra"] = self.extra
        return HEADER + "\n" + tomli_w.dumps(doc)

    @classmethod
    def from_toml(cls, text: str, source: str = SETTINGS_FILE) -> Settings:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SettingsError(f"{source}: not valid TOML ({exc})") from None
        study = doc.get("study", {})
        for name, want in (("study", dict), ("levels", list), ("extra", dict)):
            if name in doc and not isinstance(doc[name], want):
                kind = "a [study] table" if want is dict else "a list of {name, cost} tables"
                if name == "extra":
                    kind = "an [extra] table"
                raise SettingsError(
                    f"{source}: '{name}' must be {kind}, got {type(doc[name]).__name__} "
                    f"{doc[name]!r}; fix it by hand or rewrite it with `bams-cli init --force`"
                )
        _known_keys(source, doc, study)
        try:
            levels = tuple(
                Level(str(lv["name"]), float(lv["cost"])) for lv in doc.get("levels", [])
            )
            settings = cls(
                gammas=tuple(float(g) for g in study.get("gammas", [])),
                levels=levels,
                seed=int(study.get("seed", 0)),
                # A file without the key was written before "auto" (to_toml always writes
                # it): it meant 12 then and still does.
                embedding_dim=_dim(study.get("embedding_dim", 12)),
                id_column=str(study.get("id_column", "segment_id")),
                extra=dict(doc.get("extra", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SettingsError(f"{source}: malformed entry ({exc})") from None
        try:
            return settings.validate()
        except SettingsError as exc:  # name the file, not "settings"
            raise SettingsError(
                str(exc).replace("settings:", f"{source}:", 1), setting=exc.setting
            ) from None

    @classmethod
    def from_file(cls, path: Path) -> Settings:
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise SettingsError(f"{path}: not a TOML text file") from None
        return cls.from_toml(text, source=str(path))

    def with_overrides(self, **overrides: Any) -> Settings:
        """Flag > settings file: apply the flags that were given (None means not given)."""
        given = {k: v for k, v in overrides.items() if v is not None}
        return replace(self, **given).validate()


def levels_from_costs(costs: list[float], names: list[str] | None = None) -> tuple[Level, ...]:
    """Build levels from a cost list; level 0 is named "high", the others "low1", "low2" ..."""
    if names is None:
        names = ["high"] + [f"low{i}" for i in range(1, len(costs))]
    if len(names) != len(costs):
        raise OptionValueError(f"--level-names has {len(names)} names for {len(costs)} costs")
    # "high, low1" names the second level "low1": results name it without the space.
    return tuple(Level(n.strip(), float(c)) for n, c in zip(names, costs, strict=True))


def load_settings(workspace: Path) -> Settings:
    path = workspace / SETTINGS_FILE
    if not path.exists():
        from bams_cli.errors import WorkspaceError

        raise WorkspaceError(
            f"{workspace}: no {SETTINGS_FILE}; create the study with "
            f"`bams-cli init -w {workspace} --gamma ... --costs ...`"
        )
    return Settings.from_file(path)
