"""The map's scale from every source the flight has, each with its own uncertainty, combined by their variances.

A source is an estimate of the factor from the map's units to metres and its relative 1-sigma uncertainty:
- **positions**: the similarity to the GPS track. A receiver's error is not white noise: it wanders (a bias drifting
  over seconds to minutes, plus a little white noise), and a bias shared by the whole track moves the map without
  scaling it. What scales it is how the error changes along the track. With the keyframes' centred positions g_i and
  the error's covariance K, the fitted scale's relative variance is g^T K g / (g^T g)^2 (one axis at a time), exact for
  a least-squares similarity. K is the stated accuracy, correlated as exp(-|dt| / tau); a consumer receiver's tau is not
  known (seconds to minutes), so the uncertainty is the largest over that range: honest whatever the receiver does.
- **heights**: the cameras' heights above the floor plane the map sees, against the log's heights above the take-off
  point (a barometer's, good to a decimetre or so over a short flight): the floor's spread and the heights' accuracy,
  over the height. It takes the take-off point to be level with the orchard's floor.
- **row spacing**: the map's distance between neighbouring rows against the layout's (``--orchard``), where a layout is
  given: measured on the map's apples at each refresh, it scales the map's outputs (ground.orchard.register
  .scaled_to_layout), not the mapper's own frame.

:func:`combine` weighs them by their inverse variances (in log scale), leaves out a source that disagrees with the
others by more than ``AGREE_SIGMAS`` of their joint uncertainty (the one furthest out first; of two, the less certain),
and says which and why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: The range of a GPS error's correlation time the positions' uncertainty is taken over (s): from a receiver's
#: multipath (seconds) to its atmospheric and orbit errors (minutes). The largest variance over the range is used.
GPS_TAU_RANGE_S = (2.0, 600.0)
#: The share of a receiver's stated accuracy that is white noise from one fix to the next (the rest wanders).
GPS_WHITE_SHARE = 0.3
#: Sources further apart than this many sigmas of their joint uncertainty disagree: the one furthest out is left out.
AGREE_SIGMAS = 3.0


@dataclass(frozen=True)
class ScaleSource:
    """One source's estimate of the map's scale (metres per map unit) and its relative 1-sigma uncertainty."""

    name: str  # positions | heights | row_spacing
    scale: float
    sigma_rel: float
    stated: bool = True  # False: the accuracy is a stated default, the log giving none
    note: str = ""

    def as_dict(self) -> dict:
        return {"name": self.name, "scale": self.scale, "sigma_pct": 100.0 * self.sigma_rel, "stated": self.stated,
                **({"note": self.note} if self.note else {})}


@dataclass
class ScaleEstimate:
    """The sources combined: the scale, its relative 1-sigma uncertainty, each source's weight, the sources left out
    (name -> why)."""

    scale: float
    sigma_rel: float
    sources: list[ScaleSource]
    weights: dict[str, float] = field(default_factory=dict)
    left_out: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"scale": self.scale, "sigma_pct": 100.0 * self.sigma_rel,
                "sources": [{**s.as_dict(), "weight": self.weights.get(s.name, 0.0),
                             **({"left_out": self.left_out[s.name]} if s.name in self.left_out else {})}
                            for s in self.sources]}

    @property
    def heaviest(self) -> str | None:
        """The source that weighs most."""
        return heaviest_source(self.as_dict())


def heaviest_source(scale: dict) -> str | None:
    """The name of the source that weighs most in an estimate as :meth:`ScaleEstimate.as_dict` gives it (report.json's
    ``georeference_scale_from``); None where none weighs."""
    used = [s for s in scale.get("sources", []) if s.get("weight")]
    return max(used, key=lambda s: s["weight"])["name"] if used else None


def sources_of(scale: dict) -> list[ScaleSource]:
    """The sources of a ScaleEstimate as :meth:`ScaleEstimate.as_dict` gives it (report.json's)."""
    return [ScaleSource(s["name"], float(s["scale"]), float(s["sigma_pct"]) / 100.0, bool(s.get("stated", True)),
                        s.get("note", "")) for s in scale.get("sources", [])]


def positions_sigma_rel(g: np.ndarray, t: np.ndarray, sigma_m: np.ndarray | float,
                        white_share: float = GPS_WHITE_SHARE, tau_range_s=GPS_TAU_RANGE_S) -> float:
    """The relative 1-sigma of a scale fitted to GPS positions ``g`` (n, 3) taken at times ``t`` (n,) with a stated
    per-axis accuracy ``sigma_m``: g_c^T K g_c / (g_c^T g_c)^2 per axis, summed over axes, for an error whose
    ``white_share`` of the variance is white and the rest correlated as exp(-|dt| / tau), the largest over
    ``tau_range_s`` (12 correlation times on a log grid)."""
    g = np.asarray(g, float).reshape(-1, 3)
    t = np.asarray(t, float).reshape(-1)
    n = len(g)
    if n < 3:
        return float("inf")
    sig = np.broadcast_to(np.asarray(sigma_m, float), (n,))
    if not np.isfinite(sig).all():  # a position of unknown accuracy (too few keyframes to measure their scatter)
        return float("inf")
    gc = g - g.mean(0)
    den = float((gc ** 2).sum())
    if not den > 0:
        return float("inf")
    G = gc @ gc.T  # sum over the axes of g_c,i . g_c,j: each axis's error is drawn alike and apart
    S = np.outer(sig, sig)
    dt = np.abs(t[:, None] - t[None, :])
    white = white_share * float((np.diag(G) * sig ** 2).sum())
    worst = 0.0
    for tau in np.geomspace(*tau_range_s, 12):
        worst = max(worst, (1.0 - white_share) * float((G * S * np.exp(-dt / tau)).sum()))
    return float(np.sqrt(worst + white) / den)


def positions_source(scale: float, g: np.ndarray, t: np.ndarray, sigma_m: np.ndarray, stated: bool) -> ScaleSource:
    """The positions' fitted ``scale`` with :func:`positions_sigma_rel`; ``stated`` False where the log gave no
    accuracy (pomar.telemetry.base.UNSTATED_H_ACC_M was assumed)."""
    return ScaleSource("positions", float(scale), positions_sigma_rel(g, t, sigma_m), stated,
                       "" if stated else "the log states no GPS accuracy: the default was assumed")


def heights_source(scale: float, h: np.ndarray, h_sigma: np.ndarray, centres: np.ndarray, floor,
                   stated: bool = True) -> ScaleSource | None:
    """The scale that brings the cameras' heights above the map's floor (``centres`` (n, 3) in metres at ``scale``,
    ``floor`` a ground.poses.georeference.FloorPlane in the same frame) to the log's heights above take-off ``h``:
    ``scale`` x median(h) / median(heights above the floor), with the floor's spread and the heights' accuracy over
    the height as its uncertainty. None where the cameras are not above the floor."""
    h = np.asarray(h, float)
    h_map = (np.asarray(centres, float).reshape(-1, 3) - floor.point) @ floor.normal
    if not np.median(h_map) > 0:
        return None
    k = float(np.median(h) / np.median(h_map))
    rel = float(np.hypot(floor.sigma_m, np.median(h_sigma)) / np.median(h))
    return ScaleSource("heights", float(scale) * k, rel, stated,
                       "" if stated else "the log states no height accuracy: the default was assumed")


def row_spacing_source(scale: float, layout_m: float, map_m: float, map_sigma_m: float) -> ScaleSource | None:
    """The scale that brings the map's spacing between neighbouring rows (``map_m`` +- ``map_sigma_m``, measured in
    metres at ``scale``: ground.orchard.register) to the layout's ``layout_m``, the measurement's spread over the
    spacing as its uncertainty. None where it was not measured."""
    if not (layout_m and layout_m > 0 and np.isfinite(map_m) and map_m > 0 and np.isfinite(map_sigma_m)
            and map_sigma_m > 0):
        return None
    return ScaleSource("row_spacing", float(scale) * layout_m / map_m, float(map_sigma_m / map_m))


def with_source(scale: dict, source: ScaleSource) -> ScaleEstimate | None:
    """The estimate ``scale`` (ScaleEstimate.as_dict's) combined again with ``source`` (replacing one of its name)."""
    return combine([s for s in sources_of(scale) if s.name != source.name] + [source])


def combine(sources: list[ScaleSource], agree_sigmas: float = AGREE_SIGMAS) -> ScaleEstimate | None:
    """The sources' inverse-variance mean in log scale. While two or more are used and one lies further than
    ``agree_sigmas`` joint sigmas from the mean of the others, the furthest is left out, with why (of two, which lie
    equally far, the less certain). None without a usable source."""
    use = [s for s in sources if np.isfinite(s.scale) and s.scale > 0 and np.isfinite(s.sigma_rel) and s.sigma_rel > 0]
    left = {s.name: "no estimate (too little seen)" for s in sources if s not in use}
    if not use:
        return None

    def mean(ss):
        w = np.array([1.0 / s.sigma_rel ** 2 for s in ss])
        x = np.array([np.log(s.scale) for s in ss])
        return float((w * x).sum() / w.sum()), float(1.0 / np.sqrt(w.sum())), w / w.sum()

    while len(use) >= 2:
        worst, worst_z = None, agree_sigmas
        # the less certain first: two sources lie equally far from each other, and the one claiming less goes
        for s in sorted(use, key=lambda s: -s.sigma_rel):
            m, sd, _ = mean([o for o in use if o is not s])
            z = abs(np.log(s.scale) - m) / np.hypot(s.sigma_rel, sd)
            if z > worst_z:
                worst, worst_z, others = s, z, m
        if worst is None:
            break
        left[worst.name] = (f"disagrees with the others by {worst_z:.1f} sigma: {100 * (worst.scale / np.exp(others) - 1):+.1f} % "
                            f"(its uncertainty {100 * worst.sigma_rel:.1f} %)")
        use = [s for s in use if s is not worst]
    m, sd, w = mean(use)
    return ScaleEstimate(float(np.exp(m)), sd, list(sources), {s.name: float(x) for s, x in zip(use, w)}, left)
