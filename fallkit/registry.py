"""Plugin discovery through entry points.

fallkit's own robots, reward terms and samplers are registered through
fallkit's own `pyproject.toml` entry points, exactly as a third-party plugin
registers its own: there is no second, private path.

Groups:
  fallkit.robots    name -> callable returning a RobotSpec (or a RobotSpec)
  fallkit.rewards   name -> reward term, a callable (context) -> Tensor[num_envs]
  fallkit.samplers  name -> sampler factory (a callable)

Entries are listed without importing them; an entry is imported when it is
first used, so one broken plugin does not break every other robot.  Every
failure is a PluginError naming the distribution and the entry point.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from importlib.metadata import EntryPoint, distributions
from typing import Any, Callable

from fallkit.errors import PluginError

GROUPS = ("fallkit.robots", "fallkit.rewards", "fallkit.samplers")




@dataclass(frozen=True)
class Entry:
    """One registered name: where it comes from and how to load it."""

    group: str
    name: str
    distribution: str
    entry_point: EntryPoint

    @property
    def where(self) -> str:
        return f"'{self.entry_point.name} = {self.entry_point.value}' of distribution '{self.distribution}'"


# Check of a loaded value, per group: returns (the value to use, an error text or None).
# The package that owns a group's type registers its check (fallkit.robots for RobotSpec),
# so this module, below everything else, imports none of them.
Check = Callable[[Any], tuple[Any, "str | None"]]
_VALIDATORS: dict[str, Check] = {}


def validator(group: str) -> Callable[[Check], Check]:
    """Register the check that a loaded value of `group` must pass."""

    def register(fn: Check) -> Check:
        _VALIDATORS[group] = fn
        return fn

    return register


@cache
def scan(group: str) -> tuple[dict[str, Entry], dict[str, list[Entry]]]:
    """Entries of a group by name, and the names registered more than once."""
    by_name: dict[str, list[Entry]] = {}
    seen: set[tuple[str, str, str]] = set()
    for dist in distributions():
        dist_name = dist.metadata["Name"] or "?"
        for ep in dist.entry_points.select(group=group):
            # One distribution found twice on sys.path is one registration.
            key = (dist_name.lower().replace("_", "-"), ep.name, ep.value)
            if key not in seen:
                seen.add(key)
                by_name.setdefault(ep.name, []).append(Entry(group, ep.name, dist_name, ep))
    unique = {n: es[0] for n, es in by_name.items() if len(es) == 1}
    duplicated = {n: es for n, es in by_name.items() if len(es) > 1}
    return unique, duplicated


def clear_cache() -> None:
    """Forget discovered entries (after installing a plugin in a running process)."""
    scan.cache_clear()
    _load.cache_clear()


def entries(group: str) -> dict[str, Entry]:
    """All names of a group, without importing anything. Duplicates are errors."""
    unique, duplicated = scan(group)
    if duplicated:
        name, es = next(iter(duplicated.items()))
        raise PluginError(_duplicate_message(group, name, es))
    return dict(sorted(unique.items()))


def names(group: str) -> list[str]:
    """Registered names of a group, duplicates included (for listings and hints)."""
    unique, duplicated = scan(group)
    return sorted({*unique, *duplicated})


def load(group: str, name: str) -> Any:
    """The validated value registered under `name` in `group`."""
    return _load(group, name)


@cache
def _load(group: str, name: str) -> Any:
    unique, duplicated = scan(group)
    if name in duplicated:
        raise PluginError(_duplicate_message(group, name, duplicated[name]))
    if name not in unique:
        kind = group.split(".")[-1]
        known = ", ".join(names(group)) or "none"
        raise PluginError(f"unknown {kind[:-1]} '{name}'; registered {kind}: {known}")
    entry = unique[name]
    try:
        value = entry.entry_point.load()
    except Exception as exc:
        raise PluginError(f"plugin {entry.where} in group '{group}' failed to import: {type(exc).__name__}: {exc}") from exc
    check = _VALIDATORS.get(group)
    if check is not None:
        try:
            value, problem = check(value)
        except Exception as exc:  # a robot factory that raises, say
            problem = f"{type(exc).__name__}: {exc}"
        if problem:
            raise PluginError(f"plugin {entry.where} in group '{group}' is invalid: {problem}")
    return value


def _duplicate_message(group: str, name: str, es: list[Entry]) -> str:
    places = "; ".join(e.where for e in es)
    return f"name '{name}' is registered {len(es)} times in group '{group}': {places}"


# ---- the checks of each group -------------------------------------------------------


@validator("fallkit.rewards")
def _check_reward(value: Any) -> tuple[Any, str | None]:
    if not callable(value):
        return value, f"expected a reward term function, got {type(value).__name__}"
    return value, None


@validator("fallkit.samplers")
def _check_sampler(value: Any) -> tuple[Any, str | None]:
    if not callable(value):
        return value, f"expected a sampler factory (callable), got {type(value).__name__}"
    return value, None
