"""The map's scale from its sources (ground.poses.scale, issue 75), on made-up geometry whose answer is known: a pass
flown over a floor, a map of it at an unknown scale, GPS whose error wanders (a bias with a correlation time drawn per
flight, plus white noise) and a barometer's heights. The combined scale's error lies within its stated 2 sigma in 95 %
of draws, for each GPS."""

from __future__ import annotations

import numpy as np

from ground.poses.georeference import fit_similarity, floor_plane
from ground.poses.scale import ScaleSource, combine, heights_source, positions_source
from scipy.spatial.transform import Rotation


def _ou(rng, t, tau, sigma):
    """An Ornstein-Uhlenbeck path (n, 3) at times ``t``: stationary, standard deviation ``sigma``, correlation time
    ``tau``."""
    out = np.empty((len(t), 3))
    out[0] = rng.normal(0, sigma, 3)
    for i in range(1, len(t)):
        a = np.exp(-(t[i] - t[i - 1]) / tau)
        out[i] = a * out[i - 1] + np.sqrt(1 - a * a) * rng.normal(0, sigma, 3)
    return out


def _flight(rng, gps_m: float, baro_m: float = 0.1, passes: int = 1):
    """A made-up flight: keyframes every 0.5 s along ``passes`` rows 28 m long at 2 m/s, 12 m over a floor; the map is
    the truth at scale 1/s (s drawn) and turned; returns the positions' and heights' sources and the true scale."""
    legs = []
    for k in range(passes):
        x = np.arange(-14.0, 14.0, 1.0)
        legs.append(np.column_stack([x if k % 2 == 0 else -x, np.full(len(x), 6.0 * k), np.full(len(x), 12.0)]))
    C = np.concatenate(legs)
    t = np.arange(len(C)) * 0.5
    s_true = rng.uniform(0.2, 5.0)
    R = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()
    to_map = lambda X: (X - np.array([3.0, -2.0, 0.5])) @ R / s_true  # noqa: E731  (ENU -> map, R^T X / s)
    tau = float(np.exp(rng.uniform(np.log(5.0), np.log(120.0))))  # the receiver's correlation time, unknown to it
    g = C + _ou(rng, t, tau, 0.85 * gps_m) + rng.normal(0, 0.5 * gps_m, C.shape)
    sigma = np.full(len(C), gps_m)
    # the cameras' attitude (looking down, 0.5 degrees of noise), which fixes the roll about a straight pass
    B = np.array([Rotation.from_euler("xz", [np.pi + rng.normal(0, 0.01), rng.normal(0, 0.01)]).as_matrix()
                  for _ in range(len(C))])
    fit = fit_similarity(to_map(C), g, sigma, B @ R, B, np.radians(0.5)).similarity
    pos = positions_source(fit.scale, g, t, sigma, stated=True)
    # the floor the map sees: points on the ground (a few cm rough) between the rows, and canopy a metre and more up
    P = np.column_stack([rng.uniform(-20, 20, 6000), rng.uniform(-10, 10 + 6 * passes, 6000), rng.normal(0, 0.04, 6000)])
    P[::3, 2] += rng.uniform(0.8, 3.0, len(P[::3]))
    floor = floor_plane(fit.apply(to_map(P)))
    baro = rng.normal(0, baro_m) + rng.normal(0, 0.02, len(C))  # a barometer's offset over a short flight, and jitter
    hs = heights_source(fit.scale, C[:, 2] + baro, np.full(len(C), baro_m), fit.apply(to_map(C)), floor)
    return pos, hs, s_true


def test_the_combined_scale_is_within_its_stated_two_sigma_in_95_percent_of_draws():
    """200 flights for each GPS (0.2, 1 and 2 m; a barometer of 0.1 m), pooled: the error within the stated 2 sigma in
    95 % of them (an honest sigma gives 95.4 %), and in no set below 93 %; the positions alone are honest too."""
    inside, pos_inside, sig = {}, {}, {}
    for gps_m in (0.2, 1.0, 2.0):
        rng = np.random.default_rng(int(gps_m * 10))
        runs = [_flight(rng, gps_m) for _ in range(200)]
        est = [combine([pos, hs]) for pos, hs, _ in runs]
        inside[gps_m] = np.mean([abs(np.log(e.scale / s)) <= 2 * e.sigma_rel for e, (_, _, s) in zip(est, runs)])
        pos_inside[gps_m] = np.mean([abs(np.log(p.scale / s)) <= 2 * p.sigma_rel for p, _, s in runs])
        sig[gps_m] = float(np.median([e.sigma_rel for e in est]))
        assert all(not e.left_out for e in est)  # honest sources agree
    assert np.mean(list(inside.values())) >= 0.95 and min(inside.values()) >= 0.93, inside
    assert min(pos_inside.values()) >= 0.95, pos_inside
    # with a 0.1-m barometer at 12 m the combined scale is known to about 1 % whatever the GPS; with 0.2-m GPS better
    assert max(sig.values()) < 0.012 and sig[0.2] < sig[2.0], sig


def test_a_source_that_disagrees_is_left_out_and_said():
    a = ScaleSource("positions", 1.00, 0.01)
    b = ScaleSource("heights", 1.002, 0.008)
    c = ScaleSource("row_spacing", 1.10, 0.01)
    est = combine([a, b, c])
    assert set(est.weights) == {"positions", "heights"} and "row_spacing" in est.left_out
    assert "disagrees" in est.left_out["row_spacing"] and "+9." in est.left_out["row_spacing"]
    assert abs(est.scale - 1.0012) < 1e-3 and est.sigma_rel < 0.008
    d = est.as_dict()
    assert [s["weight"] for s in d["sources"]][2] == 0.0 and d["sources"][2]["left_out"]
    # weights follow the inverse variances
    assert est.weights["heights"] > est.weights["positions"]
    assert combine([ScaleSource("positions", float("nan"), 0.01)]) is None


def test_positions_of_unknown_accuracy_give_a_scale_of_unknown_accuracy_without_a_warning():
    """Too few keyframes to measure the positions' scatter leave their accuracy infinite: the positions' scale is
    then of unknown accuracy (weighs nothing), said without numpy's 'invalid value' warning in the ground's log."""
    import warnings

    g = np.column_stack([np.arange(6.0), np.zeros(6), np.full(6, 12.0)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        src = positions_source(1.0, g, np.arange(6) * 0.5, np.full(6, np.inf), stated=False)
    assert np.isinf(src.sigma_rel)
