"""The ground's command line: `ground replay` hands every ground option on to the ground process it starts."""

from __future__ import annotations

import argparse

from ground.__main__ import _ground_argv, _ground_options, _settings


def test_replay_hands_every_ground_option_to_the_ground():
    p = argparse.ArgumentParser()
    _ground_options(p)
    given = ["--track-points", "600", "--min-share-to-go-on", "0.3", "--init-frames", "4", "--init-spacing-s", "0.7",
             "--upright", "--no-revisit", "--confirm-score", "0.8", "--mapping", "inline"]
    args = p.parse_args(given)
    again = p.parse_args(_ground_argv(args))
    # every option as given, but --mapping, which the replay chooses (lock-step or live)
    assert vars(again) == {**vars(args), "mapping": p.get_default("mapping")}
    s = _settings(again)
    assert s.tracking.max_points == 600 and s.tracking.min_share_to_go_on == 0.3
    assert s.registration.init_frames == 4 and s.init_spacing_s == 0.7
    assert s.registration.upright and not s.registration.revisit and s.confirm_score == 0.8
    # switches left off stay off
    assert "--upright" not in _ground_argv(p.parse_args([]))
