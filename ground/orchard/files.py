"""The grower's own files about the orchard, read and checked together before a ground starts: the orchard layout
(``--orchard``, pomar.layout) and the trees counted by hand (``--sample-counts``, pomar.sample_counts). One that does
not read, or hand counts that cannot calibrate the load model, stop the command with one line (exit 2)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ground.orchard.calibration import DEFAULT_MODEL, CalibrationError, check_enough
from pomar.layout import LayoutRow, layout_trees, read_layout
from pomar.sample_counts import read_sample_counts


@dataclass
class OrchardFiles:
    layout: list[LayoutRow] | None = None
    layout_path: Path | None = None
    #: (row, tree) -> apples counted by hand.
    samples: dict | None = None
    samples_path: Path | None = None
    #: What the flight's log was already told of these files (a warning said once, not at every refresh).
    warned: set = field(default_factory=set)


def read_orchard_files(orchard=None, sample_counts=None, load_model: str = DEFAULT_MODEL) -> OrchardFiles:
    """The layout and the hand counts, checked: each counted tree one of the layout's, enough of them for the model.
    Hand counts need a layout (the map's own tree numbers move as the map grows)."""
    layout = read_layout(orchard) if orchard else None
    samples = None
    if sample_counts:
        if layout is None:
            raise CalibrationError(f"{sample_counts}: hand counts need the orchard's layout (--orchard FILE), whose "
                                   "tree numbers they use; for a finished map, use `python -m ground load MAP`")
        trees = layout_trees(layout)
        samples = read_sample_counts(sample_counts, trees, f"the orchard layout {orchard}")
        check_enough(samples, load_model, sample_counts)
    return OrchardFiles(layout, Path(orchard) if orchard else None, samples,
                        Path(sample_counts) if sample_counts else None)
