from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "replay_data" / "demo-flight"
SMALL_CONFIG = ROOT / "sim" / "configs" / "small.toml"


@pytest.fixture(scope="session")
def slowness():
    """How many times slower than the development machine this one runs at the start of the run (tests/machine.py):
    a test of a wall-clock behaviour slows its clock by it."""
    from tests.machine import slowness

    return slowness()


@pytest.fixture(scope="session")
def bundled_flight():
    from pomar.flight import FlightDir

    return FlightDir(BUNDLED)


@pytest.fixture(scope="session")
def small_flight(tmp_path_factory):
    """A tiny simulated flight rendered once per test session (about 5 s)."""
    from pomar.flight import FlightDir
    from sim import config
    from sim.flight import simulate_flight

    out = tmp_path_factory.mktemp("small") / "flight"
    simulate_flight(config.load(SMALL_CONFIG), out, jobs=2, progress=False)
    return FlightDir(out)


REPLAY_TEST_CONFIG = ROOT / "sim" / "configs" / "replay-test.toml"


@pytest.fixture(scope="session")
def replay_test_flight(tmp_path_factory):
    """A tiny flight for end-to-end replays (640x360, 20 frames; about 7 s to render)."""
    from pomar.flight import FlightDir
    from sim import config
    from sim.flight import simulate_flight

    out = tmp_path_factory.mktemp("replay-test") / "flight"
    simulate_flight(config.load(REPLAY_TEST_CONFIG), out, jobs=2, progress=False)
    return FlightDir(out)


@pytest.fixture(scope="session")
def replayed_test_flight(replay_test_flight, tmp_path_factory):
    """The tiny flight through both processes once per session (ONNX detector, every frame a keyframe at full
    size): (flight, output folder, report)."""
    from ground.replay import replay

    out = tmp_path_factory.mktemp("replayed") / "out"
    rep = replay(replay_test_flight.path, out, detector="onnx", keyframe_every=1, keyframe_width=0, quiet=True)
    return replay_test_flight, out, rep


#: Test files that replay flights or run the nodes end to end: the `system` tier (make test runs them,
#: make check leaves them out).
SYSTEM_FILES = {"test_readme_commands.py", "test_whole_plot.py", "test_hostile_link.py", "test_transport_security.py",
                "test_replay_errors.py", "test_live.py", "test_player.py", "test_ground_node.py", "test_onboard_node.py",
                "test_export.py", "test_registration.py"}
#: Fixtures that render or replay a flight: a test using one is a `system` test wherever it is.
SYSTEM_FIXTURES = {"small_flight", "replay_test_flight", "replayed_test_flight"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in SYSTEM_FILES or SYSTEM_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.system)
