"""Every registered plugin of every role against every plugin of the others: the choices a run
makes (`factors`: the roles, the mapper's parts, the preset, the mode) and a small set of
combinations in which every pair of choices appears at least once (`pairwise`), so that a plugin
joins the composition matrix (tests, docs/composition.md) by registering.

The dataset role is left out: the matrix runs on a few frames of the built-in synthetic sequence,
the one input every machine has (the other datasets need their recordings).
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from importlib.resources import files
from itertools import combinations

from slamkit.registry.discovery import Registry
from slamkit.roles import PARTS, ROLES

#: The run modes that build a map (mode=localize tracks in a saved one: tests/e2e/test_localization.py).
MODES = ("sequential", "realtime")


@dataclass(frozen=True)
class Factor:
    """One choice of a run: `key` is its override (`tracker`, `mapper/strategy`, `preset`, `mode`),
    `values` its options; `requires` = (factor key, options) when it applies only under those
    (a mapper's part under a mapper that has the part)."""

    key: str
    values: tuple[str, ...]
    requires: tuple[str, tuple[str, ...]] | None = None

    def applies(self, combination: dict[str, str]) -> bool:
        return self.requires is None or combination.get(self.requires[0]) in self.requires[1]


def presets() -> tuple[str, ...]:
    """The presets shipped in the config tree (conf/preset/*.yaml)."""
    folder = files("slamkit.conf") / "preset"
    return tuple(sorted(f.name.removesuffix(".yaml") for f in folder.iterdir() if f.name.endswith(".yaml")))


def factors(registry: Registry) -> list[Factor]:
    """Every role's registered plugins (the dataset's aside: module docstring), every part's under
    the mappers that have it, the presets and the modes."""
    found = [Factor(role.group, tuple(sorted(registry.plugins[role.key])))
             for role in ROLES if role.part_of is None and role.key != "dataset"]
    mappers = {name: entry.spec.cls for name, entry in registry.plugins["mapper"].items()}
    for part in PARTS:
        owners = tuple(sorted(name for name, cls in mappers.items() if part.key in getattr(cls, "parts", ())))
        if owners and registry.plugins[part.key]:
            found.append(Factor(part.group, tuple(sorted(registry.plugins[part.key])), ("mapper", owners)))
    return [*found, Factor("preset", presets()), Factor("mode", MODES)]


def _possible(a: Factor, va: str, b: Factor, vb: str) -> bool:
    """Whether choices a=va and b=vb can be made in one run (a part needs a mapper that has it)."""
    return ((a.requires is None or a.requires[0] != b.key or vb in a.requires[1])
            and (b.requires is None or b.requires[0] != a.key or va in b.requires[1]))


def pairs(found: list[Factor]) -> set[tuple[tuple[str, str], tuple[str, str]]]:
    """Every pair of choices of two factors that one run can make."""
    return {((a.key, va), (b.key, vb)) for a, b in combinations(found, 2) for va in a.values for vb in b.values
            if _possible(a, va, b, vb)}


def covered_pairs(combination: dict[str, str], found: list[Factor]) -> set:
    """The pairs of choices a combination makes, each in `pairs`' order."""
    chosen = [(f.key, combination[f.key]) for f in found if f.key in combination]
    return set(combinations(chosen, 2))


def pairwise(found: list[Factor], seed: int = 0, candidates: int = 40, covered: set = frozenset(),
             refused: set = frozenset()) -> list[dict[str, str]]:
    """Combinations (factor key -> option) in which every pair of `pairs(found)` not already
    `covered` appears: each the best of `candidates` built greedily (each choice the one that
    covers most pairs not yet covered), until none is left. `refused`: choices ((key, option))
    and pairs of choices (frozensets of two) known to be refused, which no combination makes
    (and whose pairs count as covered). The same list for the same arguments."""
    rng = random.Random(seed)

    def allowed(combination: dict[str, str]) -> bool:
        chosen = [(k, v) for k, v in combination.items()]
        return not any(c in refused for c in chosen) and not any(
            frozenset(p) in refused for p in combinations(chosen, 2))

    uncovered = {p for p in pairs(found) - set(covered)
                 if p[0] not in refused and p[1] not in refused and frozenset(p) not in refused}
    order = sorted(found, key=lambda f: f.requires is not None)  # a part after the mapper it needs
    chosen: list[dict[str, str]] = []
    while uncovered:
        best, best_gain = None, 0
        for _ in range(candidates):
            combination: dict[str, str] = {}
            for factor in order:
                if not factor.applies(combination):
                    continue
                values = [v for v in factor.values if allowed({**combination, factor.key: v})]
                rng.shuffle(values)
                if not values:
                    break
                combination[factor.key] = max(values, key=lambda v: len(
                    covered_pairs({**combination, factor.key: v}, found) & uncovered))
            else:
                gain = len(covered_pairs(combination, found) & uncovered)
                if gain > best_gain:
                    best, best_gain = combination, gain
        if best is None:  # what is left cannot be made without a refused choice
            break
        uncovered -= covered_pairs(best, found)
        chosen.append(best)
    return chosen
