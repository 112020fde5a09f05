"""The composition matrix's combinations (slamkit.registry.combinations): every pair of choices
in some combination, a part only under a mapper that has it, refused choices never made, the same
list every time, and a plugin that registers joins it. The runs: tests/e2e/test_composition_matrix.py."""

from __future__ import annotations

from itertools import combinations

from slamkit.registry.combinations import Factor, factors, pairs, pairwise
from slamkit.registry.discovery import discover

FACTORS = [Factor("tracker", ("a", "b", "c")), Factor("mapper", ("m", "none")), Factor("mode", ("s", "r")),
           Factor("mapper/part", ("p", "q", "x"), ("mapper", ("m",)))]


def _covered(rows):
    return {p for row in rows for p in combinations([(f.key, row[f.key]) for f in FACTORS if f.key in row], 2)}


def test_every_pair_one_run_can_make_is_in_some_combination_and_parts_only_under_their_mapper():
    rows = pairwise(FACTORS)
    assert pairs(FACTORS) <= _covered(rows)
    assert all(("mapper/part" in row) == (row["mapper"] == "m") for row in rows)
    assert len(rows) < 3 * 2 * 2 * 3  # fewer than every combination
    assert rows == pairwise(FACTORS)  # the same every time


def test_refused_choices_and_pairs_are_never_made_and_covered_pairs_not_again():
    refused = {("mapper/part", "x"), frozenset({("tracker", "c"), ("mode", "r")})}
    rows = pairwise(FACTORS, refused=refused)
    assert not any(row.get("mapper/part") == "x" or (row["tracker"], row["mode"]) == ("c", "r") for row in rows)
    wanted = {p for p in pairs(FACTORS) if ("mapper/part", "x") not in p and frozenset(p) not in refused}
    assert wanted <= _covered(rows)
    assert pairwise(FACTORS, covered=pairs(FACTORS)) == []


def test_a_registered_plugin_joins_the_matrix(plugin_dir):
    tracker = next(f for f in factors(discover()) if f.key == "tracker")
    assert "still" in tracker.values and "gicp" in tracker.values
