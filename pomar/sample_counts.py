"""The sample-count file (issue 59): the apples a grower counted by hand on a few trees, one line a tree.

    row,tree,apples
    3,12,148

Rows and trees are numbered as the map's ``trees.csv`` numbers them (an orchard layout's numbers, when the ground
was given one). ``sim counts`` writes one from a simulated orchard's truth; the ground calibrates its estimate of each
tree's load with it. :func:`read_sample_counts` checks it: a line that does not parse, a negative or non-numeric
count, a tree given twice, or (given the map's trees) a tree the map does not have: one line naming the line.
"""

from __future__ import annotations

import csv
from pathlib import Path

from pomar.cli import InputError
from pomar.user_csv import user_csv

COLUMNS = ["row", "tree", "apples"]


class SampleCountsError(InputError, ValueError):
    """A sample-count file that does not read: the message names the file, its line and what is wrong."""


def read_sample_counts(path, trees: set[tuple[int, int]] | None = None,
                       trees_from: str = "the map's trees.csv") -> dict[tuple[int, int], int]:
    """(row, tree) -> apples counted, in the file's order; ``trees``: the (row, tree) numbers of the orchard (as
    ``trees_from`` gives them), each sample's tree must be one of them."""
    path = Path(path)
    out: dict[tuple[int, int], int] = {}
    lines: dict[tuple[int, int], int] = {}
    for line, d in user_csv(path, COLUMNS, SampleCountsError, "a sample-count file"):
        key = (_whole(path, line, d, "row"), _whole(path, line, d, "tree"))
        apples = _whole(path, line, d, "apples")
        if apples < 0:
            raise SampleCountsError(f"{path}:{line}: apples {d['apples']} is negative")
        if key in out:
            raise SampleCountsError(f"{path}:{line}: row {key[0]} tree {key[1]} is given twice (first on line "
                                    f"{lines[key]})")
        if trees is not None and key not in trees:
            raise SampleCountsError(f"{path}:{line}: no tree {key[1]} in row {key[0]} in {trees_from}")
        out[key], lines[key] = apples, line
    if not out:
        raise SampleCountsError(f"{path}: no trees counted")
    return out


def _whole(path: Path, line: int, d: dict, key: str) -> int:
    text = (d.get(key) or "").strip()
    try:
        return int(text)
    except ValueError:
        raise SampleCountsError(f"{path}:{line}: {key} {text!r} is not a whole number") from None


def write_sample_counts(counts: list[dict], path) -> None:
    """Write ``counts`` (each {row, tree, apples})."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(counts)
