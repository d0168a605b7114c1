"""A grower's hand counts of a few trees, from a simulated flight's truth (truth/trees.csv): the sample-count file
(``row,tree,apples``) the ground calibrates its estimate of the load with (issue 59).

    python -m sim counts FLIGHT_DIR --trees 3:5 4:12 --out counts.csv
    python -m sim counts FLIGHT_DIR --random 10 --seed 1 --count-error-cv 0.05 --out counts.csv

Rows and trees are numbered as the truth numbers them (rows 1..N across the orchard, trees 1.. from each row's -y
end). ``--count-error-cv`` adds a human's counting error: each count is the true load times a normal factor of mean
1 and this coefficient of variation (0: exact counts).
"""

from __future__ import annotations

import numpy as np

from pomar.cli import InputError


class CountsError(InputError, ValueError):
    """Trees asked for that the flight does not have, or a flight without the trees' truth."""


def parse_tree(text: str) -> tuple[int, int]:
    """``ROW:TREE`` -> (row, tree)."""
    try:
        row, tree = (int(x) for x in text.split(":"))
    except ValueError:
        raise CountsError(f"--trees: {text!r} is not ROW:TREE (two whole numbers, e.g. 3:12)") from None
    return row, tree


def sample_counts(flight, trees: list[tuple[int, int]] | None = None, random: int = 0, seed: int = 0,
                  count_error_cv: float = 0.0) -> list[dict]:
    """The counts of ``trees`` (or of ``random`` trees drawn with ``seed``) of a flight directory (pomar.flight.FlightDir),
    each {row, tree, apples}, in the order asked (drawn trees by row and tree)."""
    from pomar.flight import FlightFormatError

    try:
        t = flight.truth_trees()
    except FlightFormatError as exc:
        raise CountsError(f"{exc} (a flight rendered before the trees' truth: render it again)") from None
    load = {(int(r), int(k)): int(n) for r, k, n in zip(t["row"], t["tree"], t["apples"])}
    rng = np.random.default_rng(seed)
    if trees:
        missing = [f"{r}:{k}" for r, k in trees if (r, k) not in load]
        if missing:
            raise CountsError(f"{flight.truth_dir / 'trees.csv'}: no tree {', '.join(missing)} (rows 1..{max(t['row'])}, "
                              f"trees 1..{max(t['tree'])})")
        if len(set(trees)) < len(trees):
            raise CountsError("--trees: a tree is asked for twice")
    else:
        if not 0 < random <= len(load):
            raise CountsError(f"--random must be 1..{len(load)} (the orchard's trees), got {random}")
        keys = sorted(load)
        trees = sorted(keys[i] for i in rng.choice(len(keys), random, replace=False))
    if count_error_cv < 0:
        raise CountsError(f"--count-error-cv must be >= 0, got {count_error_cv}")
    out = []
    for r, k in trees:
        n = load[(r, k)]
        if count_error_cv > 0:
            n = max(0, int(round(n * rng.normal(1.0, count_error_cv))))
        out.append({"row": r, "tree": k, "apples": n})
    return out
