"""The load estimate from hand counts (ground/orchard/calibration.py) and the sample-count file (pomar/sample_counts.py)
on made-up orchards whose true loads are known: the intervals hold what they say, the hand counts stay as counted, and
every broken line of a sample-count file is named."""

from __future__ import annotations

import numpy as np
import pytest

from ground.orchard.calibration import CalibrationError, estimate_load
from pomar.sample_counts import SampleCountsError, read_sample_counts


def _orchard(rng, rows=4, per_row=25, row_means=None, vigour_cv=0.25, coverage=None):
    """Trees whose load is Poisson about their row's mean (120 unless ``row_means``) times a tree's vigour (gamma, CV
    ``vigour_cv``), of which the camera sees 40 % of the share its coverage shows (uniform 0.3-1, or ``coverage`` for
    every tree): (trees' records, true loads)."""
    trees, load = [], []
    for r in range(1, rows + 1):
        for k in range(1, per_row + 1):
            mean = row_means[r - 1] if row_means else 120.0
            n = rng.poisson(mean * rng.gamma(1 / vigour_cv ** 2, vigour_cv ** 2))
            cov = rng.uniform(0.3, 1.0) if coverage is None else coverage
            seen = rng.binomial(n, 0.4 * cov)
            trees.append({"row": r, "tree": k, "count": seen, "coverage": cov})
            load.append(n)
    return trees, np.array(load, float)


@pytest.mark.parametrize("model,coverage", [("ratio", 0.7), ("linear", 0.7), ("linear", None), ("coverage", None)])
def test_the_90_percent_intervals_hold_the_true_loads_about_90_percent_of_the_time(model, coverage):
    """200 orchards, 10 trees counted on each, each model where it holds (the count in proportion to the load where
    every tree is seen alike; the count over the coverage where the coverage varies): the trees' intervals hold their
    true load 80-97 % of the time, the rows' and the flight's too; the counted trees keep their hand counts."""
    rng = np.random.default_rng(7)
    tree_in, row_in, flight_in = [], [], []
    for _ in range(200):
        trees, load = _orchard(rng, coverage=coverage)
        pick = rng.choice(len(trees), 10, replace=False)
        samples = {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in pick}
        est = estimate_load(trees, samples, model)
        t = est["trees"]
        assert all(t[i]["load"] == load[i] == t[i]["hand_count"] for i in pick)
        free = np.setdiff1d(np.arange(len(trees)), pick)
        tree_in += [t[i]["load_lo"] <= load[i] <= t[i]["load_hi"] for i in free]
        for r, e in est["rows"].items():
            truth = load[[x["row"] == r for x in trees]].sum()
            row_in.append(e["load_lo"] <= truth <= e["load_hi"])
        flight_in.append(est["flight"]["load_lo"] <= load.sum() <= est["flight"]["load_hi"])
    for name, hits in (("trees", tree_in), ("rows", row_in), ("flight", flight_in)):
        assert 0.80 <= np.mean(hits) <= 0.97, (model, name, np.mean(hits))


def test_the_coverage_model_beats_the_ratio_where_the_seen_share_follows_coverage():
    """Where the camera sees 40 % of what the coverage shows, the count over coverage predicts the load better
    (leave-one-out error of 30 counted trees) than the count alone."""
    rng = np.random.default_rng(3)
    trees, load = _orchard(rng, rows=6)
    pick = rng.choice(len(trees), 30, replace=False)
    samples = {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in pick}
    ratio, cov = (estimate_load(trees, samples, m)["loo"]["rms_error"] for m in ("ratio", "coverage"))
    assert cov < ratio, (cov, ratio)


def test_trees_the_camera_never_saw_take_the_level_of_those_counted_among_them():
    """Rows 1-4 seen alike (their count in proportion to their load, so the seen trees' line runs near the origin),
    rows 5-8 never seen and twice as loaded; 12 trees counted as choose-trees names them (some in every row), 40
    orchards: the unseen rows' loads come from their counted trees' level, not from the line at a count of 0 (which
    those trees only pull towards them: 9 % low in the median): their median bias within 5 %, their median error
    under 15 %, and their intervals hold them at least 70 % of the time (the residual spread is pooled with the seen
    trees', whose loads, half as large, spread less)."""
    from ground.orchard.choose import choose_trees

    rng = np.random.default_rng(4)
    errors, held = [], []
    for _ in range(40):
        trees, load = _orchard(rng, rows=8, row_means=(100, 100, 100, 100, 200, 200, 200, 200), coverage=0.7)
        for t in trees:
            if t["row"] >= 5:
                t.update(count=0, coverage=0.0)
        picked = choose_trees(trees, 12)
        est = estimate_load(trees, {(t["row"], t["tree"]): int(load[(t["row"] - 1) * 25 + t["tree"] - 1])
                                    for t in picked}, "linear")
        for r in range(5, 9):
            truth, e = load[(r - 1) * 25:r * 25].sum(), est["rows"][r]
            errors.append((e["load"] - truth) / truth)
            held.append(e["load_lo"] <= truth <= e["load_hi"])
    bias, error = np.median(errors), np.median(np.abs(errors))
    assert abs(bias) < 0.05 and error < 0.15 and np.mean(held) >= 0.7, (bias, error, np.mean(held))


def test_a_load_never_falls_as_the_count_rises_and_says_so():
    """Ten counted trees whose loads happen to fall as their counts rise (issue 71's held-out flight: load = 9.0 - 0.78
    x count): the slope is held at 0, every other tree takes the sample's level (a tree with 5 apples seen is not
    estimated below one with none), and the report says which coefficient was held and what the sample alone gave."""
    from ground.orchard.calibration import apply_load

    trees = [{"row": 1 + k // 10, "tree": 1 + k % 10, "count": k % 6, "coverage": 0.5} for k in range(30)]
    samples = {(1, 1 + k): int(round(9.0 - 0.78 * (k % 6))) + (k % 2) for k in range(10)}
    est = estimate_load(trees, samples, "linear")
    assert est["coefficients"][1] == 0.0 and est["constraints"]["held_at_0"] == ["slope (count)"]
    assert "the sample alone gives -0." in est["constraints"]["why"]
    free = [e for k, e in enumerate(est["trees"]) if k >= 10]
    mean = np.mean(list(samples.values()))
    assert all(e["load"] == pytest.approx(mean) and e["load_lo"] < mean < e["load_hi"] for e in free)
    report = apply_load(trees, [{"row": 1}, {"row": 2}, {"row": 3}], est)
    assert report["constraints"]["held_at_0"] == ["slope (count)"]
    # where the sample supports a slope, none is held
    rising = {(1, 1 + k): 3 + 2 * (k % 6) + (k % 2) for k in range(10)}
    est = estimate_load(trees, rising, "linear")
    assert est["constraints"]["held_at_0"] == [] and est["coefficients"][1] > 0


@pytest.mark.parametrize("model", ["linear", "ratio"])
def test_trees_never_seen_none_of_them_counted_take_the_samples_level_never_0(model):
    """Rows whose first trees the camera never saw, none of those counted (issue 71's row 1, written as 0): each takes
    the counted trees' level with an interval, never 0, over 100 orchards; their rows' intervals hold the true load
    at least 80 % of the time. The ratio model too (it once wrote them b x 0: heavy-tune flights' rows 95 % low)."""
    rng = np.random.default_rng(11)
    held = []
    for _ in range(100):
        trees, load = _orchard(rng, rows=4, coverage=0.7)
        for t in trees:
            if t["tree"] <= 5:
                t.update(count=0, coverage=0.0)
        seen = [i for i, t in enumerate(trees) if t["coverage"] > 0]
        pick = rng.choice(seen, 10, replace=False)
        est = estimate_load(trees, {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in pick}, model)
        level = np.mean(load[pick])
        for t, e in zip(trees, est["trees"]):
            if t["coverage"] == 0:
                assert e["load"] == pytest.approx(level) and 0 < e["load_lo"] < level < e["load_hi"]
        for r, e in est["rows"].items():
            held.append(e["load_lo"] <= load[[t["row"] == r for t in trees]].sum() <= e["load_hi"])
    assert est["never_seen"]["trees"] == 20 and est["never_seen"]["estimated_by"].startswith("the sample's level")
    assert np.mean(held) >= 0.8, np.mean(held)


def test_a_rows_interval_carries_the_error_its_trees_share():
    """Rows that differ in load (a lognormal level a row, sd 0.3) and are seen unequally (a lognormal visibility, sd
    0.3: one seen nearer, another from its far side), heavy trees (120 apples), 20 trees counted as choose-trees names
    them, 100 orchards: each row's trees share its error, which a sum of independent residuals averages away (its
    rows' intervals held 0.54-0.57 of the true loads, its flights' 0.73-0.79); with the row's variance component the
    rows' 90 % intervals hold 0.85-0.97 of them, and the flights' at least 0.85."""
    from ground.orchard.choose import choose_trees

    rng = np.random.default_rng(21)
    rows_in, flight_in = [], []
    for _ in range(100):
        vis, level = rng.lognormal(0.0, 0.3, 6), 120.0 * rng.lognormal(0.0, 0.3, 6)
        trees, load = [], []
        for r in range(1, 7):
            for k in range(1, 31):
                n = rng.poisson(level[r - 1] * rng.gamma(16.0, 1 / 16.0))
                cov = rng.uniform(0.25, 0.75)
                trees.append({"row": r, "tree": k, "count": int(rng.binomial(n, min(1.0, 0.15 * vis[r - 1] * cov / 0.5))),
                              "coverage": cov})
                load.append(n)
        load = np.array(load, float)
        est = estimate_load(trees, {(t["row"], t["tree"]): int(load[(t["row"] - 1) * 30 + t["tree"] - 1])
                                    for t in choose_trees(trees, 20)}, "linear")
        for r, e in est["rows"].items():
            rows_in.append(e["load_lo"] <= load[(r - 1) * 30:r * 30].sum() <= e["load_hi"])
        flight_in.append(est["flight"]["load_lo"] <= load.sum() <= est["flight"]["load_hi"])
    assert 0.85 <= np.mean(rows_in) <= 0.97 and np.mean(flight_in) >= 0.85, (np.mean(rows_in), np.mean(flight_in))


def test_too_few_hand_counts_say_how_many_the_model_needs():
    trees, load = _orchard(np.random.default_rng(0), rows=1)
    with pytest.raises(CalibrationError, match="3 trees counted by hand: the 'linear' model needs at least 4"):
        estimate_load(trees, {(1, k): int(load[k - 1]) for k in (1, 2, 3)}, "linear")
    with pytest.raises(CalibrationError, match="every one of the 5 trees counted by hand holds 0 apples"):
        estimate_load(trees, {(1, k): 0 for k in range(1, 6)}, "linear")


@pytest.mark.parametrize("text,says", [
    ("row,tree,apples\n1,2,x\n", ":2: apples 'x' is not a whole number"),
    ("row,tree,apples\n1,2,-4\n", ":2: apples -4 is negative"),
    ("row,tree,apples\n1,2,40\n1,3,50\n1,2,41\n", ":4: row 1 tree 2 is given twice (first on line 2)"),
    ("row,tree,apples\n1,99,40\n", ":2: no tree 99 in row 1 in the map's trees.csv"),
    ("row,tree\n1,2\n", ":1: a sample-count file needs the columns row,tree,apples"),
    ("row,tree,apples\n", ": no trees counted"),
])
def test_a_broken_sample_count_file_is_one_line_naming_its_line(tmp_path, text, says):
    path = tmp_path / "counts.csv"
    path.write_text(text)
    with pytest.raises(SampleCountsError) as e:
        read_sample_counts(path, {(1, k) for k in range(1, 11)})
    assert str(e.value).startswith(str(path)) and says in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_good_sample_count_file_reads_in_its_order(tmp_path):
    path = tmp_path / "counts.csv"
    path.write_text("row,tree,apples\n3,12,148\n1,2,0\n")
    assert list(read_sample_counts(path).items()) == [((3, 12), 148), ((1, 2), 0)]


def test_the_chosen_trees_span_the_counts_and_rows_and_estimate_no_worse_than_random_draws():
    """10 trees chosen from 100 on 4 rows of different mean loads: every row has some, the chosen counts span the
    orchard's, and over 30 orchards the median per-row load error they give is within 5 % of that of random draws of
    10 trees (20 an orchard), where the 10 trees the camera saw least give far more. (Issue 59 asks more of it on the
    evaluation flights: no larger error than the median random draw on each.)"""
    from ground.orchard.choose import choose_trees

    rng = np.random.default_rng(11)
    chosen_error, random_error, worst_error = [], [], []
    for _ in range(30):
        trees, load = _orchard(rng, row_means=(80, 120, 160, 100))
        chosen = choose_trees(trees, 10)
        assert len(chosen) == 10 and {t["row"] for t in chosen} == {1, 2, 3, 4}
        counts = np.array([t["count"] for t in trees])
        got = np.array([t["count"] for t in chosen])
        assert got.min() <= np.percentile(counts, 10) and got.max() >= np.percentile(counts, 90)

        def row_error(picked):
            est = estimate_load(trees, {(t["row"], t["tree"]): int(load[(t["row"] - 1) * 25 + t["tree"] - 1])
                                        for t in picked})
            truth = {r: load[[x["row"] == r for x in trees]].sum() for r in est["rows"]}
            return np.median([abs(e["load"] - truth[r]) / truth[r] for r, e in est["rows"].items()])

        chosen_error.append(row_error(chosen))
        worst_error.append(row_error(sorted(trees, key=lambda t: t["count"])[:10]))
        random_error.append(np.median([row_error([trees[i] for i in rng.choice(len(trees), 10, replace=False)])
                                       for _ in range(20)]))
    got, random, worst = np.median(chosen_error), np.median(random_error), np.median(worst_error)
    assert got <= 1.05 * random and worst > 1.5 * random, (got, random, worst)


def test_every_row_gets_a_tree_to_count_the_unseen_ones_placed_along_them():
    """8 rows of 25 trees, the camera saw rows 4 and 5 only: of 10 trees, one in each row (the rows never seen: trees
    placed systematically along them, the count says nothing there), the other two among the trees the camera saw; of 4
    trees, 4 rows spread over the 8."""
    from ground.orchard.choose import choose_trees

    rng = np.random.default_rng(5)
    trees, _ = _orchard(rng, rows=8)
    for t in trees:
        if t["row"] not in (4, 5):
            t.update(count=0, coverage=0.0)
    chosen = choose_trees(trees, 10)
    assert sorted({t["row"] for t in chosen}) == list(range(1, 9)) and len(chosen) == 10
    # the six unseen rows' trees at 1/12, 3/12, ... 11/12 of their rows (25 trees): one of each place
    assert sorted(t["tree"] for t in chosen if t["row"] not in (4, 5)) == [3, 7, 11, 15, 19, 23]
    assert sum(t["row"] in (4, 5) for t in chosen) == 4
    assert [t["row"] for t in choose_trees(trees, 4)] == [1, 3, 6, 8]
    # drawn at random where the rule takes a middle (the benchmark's many samples): the same design, other trees
    draws = [choose_trees(trees, 10, rng=np.random.default_rng(s)) for s in range(5)]
    for d in draws:
        assert sorted({t["row"] for t in d}) == list(range(1, 9)) and len(d) == 10
        assert sum(t["row"] in (4, 5) for t in d) == 4 and all(t["coverage"] > 0 for t in d if t["row"] in (4, 5))
    assert len({tuple((t["row"], t["tree"]) for t in d) for d in draws}) == 5


def test_each_rows_fruit_size_and_kilograms_follow_its_apples_diameters():
    """Two rows, apples of 60-70 mm and of 75-85 mm (a few with no fit): each row's median, its shares of the size
    classes, the mean mass of its apples by pomar.fruit's relation, and its kilograms the load times that mass."""
    from ground.orchard.size import row_sizes
    from pomar.fruit import apple_mass_kg

    rng = np.random.default_rng(2)
    d = np.concatenate([rng.uniform(0.060, 0.070, 200), rng.uniform(0.075, 0.085, 200)])
    row = np.repeat([3, 4], 200)
    radius = d / 2
    radius[[0, 250]] = np.nan
    # two fits that failed (a heavy tuning flight's map held an apple of 1.3 m): left out of every size and mass
    table = {"id": np.arange(402), "row": np.append(row, [3, 0]), "radius_m": np.append(radius, [0.65, 0.3])}
    rows = [{"row": 3, "load": 1000.0, "load_lo": 900.0, "load_hi": 1100.0}, {"row": 4},
            {"row": 5, "load": 500.0, "load_lo": 400.0, "load_hi": 600.0}]  # row 5: no apple measured
    flight = row_sizes(table, rows, {3: "Fuji"})
    a, b, c = rows
    assert abs(a["diameter_mm"] - 65) < 1 and abs(b["diameter_mm"] - 80) < 1
    assert a["share_60_70"] == 1.0 and a["share_lt60"] == a["share_70_80"] == a["share_gt80"] == 0
    assert 0.4 < b["share_70_80"] < 0.6 and abs(b["share_70_80"] + b["share_gt80"] - 1) < 1e-9
    assert np.isclose(a["apple_kg"], apple_mass_kg(d[1:200], "Fuji").mean())
    assert np.isclose(a["kg"], 1000 * a["apple_kg"]) and np.isclose(a["kg_hi"], 1100 * a["apple_kg"])
    assert np.isnan(b["kg"]) and np.isnan(flight["kg"])  # no load, no kilograms
    # a row whose fruit the camera never measured: no size, its kilograms from the flight's apples
    assert np.isnan(c["diameter_mm"]) and np.isclose(c["apple_kg"], apple_mass_kg(d[np.isfinite(radius)]).mean())
    assert np.isclose(c["kg"], 500 * c["apple_kg"])
    assert flight["apples_measured"] == 398 and 70 < flight["diameter_mm"] < 76 and flight["apples_far_out"] == 2
    # the median's 90 % interval from its apples; the map scale's uncertainty (2 %) widens it, and the kilograms' by
    # three times as much (the cube)
    assert 63 < a["diameter_mm_lo"] < a["diameter_mm"] < a["diameter_mm_hi"] < 67
    wide = [{k: v for k, v in r.items() if k in ("row", "load", "load_lo", "load_hi")} for r in rows]
    row_sizes(table, wide, {3: "Fuji"}, scale_sigma_rel=0.02)
    w = wide[0]
    assert np.isclose(w["diameter_mm_lo"], 65 * (1 - 1.6449 * 0.02), atol=0.6) and w["diameter_mm_hi"] > a["diameter_mm_hi"] + 1.5
    assert np.isclose(w["kg"], a["kg"]) and np.isclose(w["kg_hi"] / w["kg"] - 1, np.hypot(0.1, 3 * 1.6449 * 0.02))


def test_the_yield_score_compares_loads_intervals_sizes_and_kilograms_with_the_truth():
    """score_yield on records as trees.csv and rows.csv give them: a tree counted by hand is left out of the trees'
    figures; a row whose interval holds its true load is covered, one that misses it is not; sizes and kilograms
    against the truth's, and the constant median's error beside the rows'."""
    from ground.evaluation.yield_score import score_yield

    truth = {"trees": {(1, 1): (100, 20.0), (1, 2): (120, 24.0), (1, 3): (90, 18.0), (2, 1): (50, 9.0)},
             "rows": {1: {"diameters_m": np.full(310, 0.080), "load": 310, "kg": 62.0},
                      2: {"diameters_m": np.full(50, 0.065), "load": 50, "kg": 9.0}}}
    trees = [{"row": "1", "tree": "1", "hand_count": "100", "load": "100"},
             {"row": "1", "tree": "2", "hand_count": "nan", "load": "110"},
             {"row": "1", "tree": "3", "hand_count": "nan", "load": "95"},
             {"row": "2", "tree": "1", "hand_count": "nan", "load": "70"}]
    rows = [{"row": "1", "load": "305", "load_lo": "280", "load_hi": "330", "diameter_mm": "79", "kg": "61"},
            {"row": "2", "load": "70", "load_lo": "60", "load_hi": "80", "diameter_mm": "66", "kg": "12"}]
    s = score_yield(trees, rows, truth)
    assert s["trees"]["n"] == 3 and s["trees"]["median_abs_error"] == 10.0
    a, b = s["rows"]
    assert a["covered"] and not b["covered"] and s["coverage"] == 0.5
    assert np.isclose(a["load_error"], -5 / 310) and np.isclose(b["load_error"], 0.4)
    assert np.isclose(a["diameter_error_mm"], -1.0) and np.isclose(b["diameter_error_mm"], 1.0)
    assert np.isclose(a["constant_error_mm"], 72.5 - 80) and np.isclose(b["constant_error_mm"], 72.5 - 65)
    assert np.isclose(a["kg_error"], -1 / 62) and np.isclose(b["kg_error"], 3 / 9)


def test_the_trees_to_count_for_a_total_within_10_percent_give_it():
    """The flight's ``trees_for_target``, from 10 counted trees (the median over 20 samples): counting that many brings
    the flight's 90 % interval within 10 % of its load in at least 80 % of 40 draws, and a third as many does not (the
    suggestion errs on the safe side, not wildly)."""
    rng = np.random.default_rng(11)
    trees, load = _orchard(rng, rows=6, per_row=40, vigour_cv=0.4)

    def flight(k):
        pick = rng.choice(len(trees), k, replace=False)
        return estimate_load(trees, {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in pick}, "linear")["flight"]

    first = [flight(10) for _ in range(20)]
    assert all(f["load_hi"] - f["load"] > 0.1 * f["load"] for f in first)
    need = int(np.median([f["trees_for_target"] for f in first]))
    assert 10 < need < len(trees)

    def widths(k):
        return np.array([(f["load_hi"] - f["load"]) / f["load"] for f in (flight(k) for _ in range(40))])

    assert np.mean(widths(need) <= 0.10) >= 0.8, need
    assert np.median(widths(need // 3)) > 0.10, need


def test_more_trees_keep_those_counted_already():
    """Ten trees chosen and counted, then 16 asked for with them: the ten are among the 16, and the six more lie in
    the rows and over the counts as the rule spreads them (no tree twice)."""
    from ground.orchard.choose import choose_trees

    trees, _ = _orchard(np.random.default_rng(1), rows=6)
    first = {(t["row"], t["tree"]) for t in choose_trees(trees, 10)}
    more = [(t["row"], t["tree"]) for t in choose_trees(trees, 16, counted=first)]
    assert len(more) == len(set(more)) == 16 and first <= set(more)
