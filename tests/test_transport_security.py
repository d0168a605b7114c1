"""The link's security, on loopback with real zenoh: the ground listens only where it is told, and the shipped
TLS + user/password configs (docs/zenoh/) let the flight through with the right credentials and nothing
through without them. Certificates are made at test time by docs/zenoh/make-certs.sh."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ground.replay import stop_process
from pomar import transport, wire

ROOT = Path(__file__).resolve().parents[1]
ZENOH_DOCS = ROOT / "docs" / "zenoh"


def listening_ports(pid: int) -> set[tuple[str, int]]:
    """(address, port) of the TCP sockets process ``pid`` listens on, from /proc."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = set()
    for table, v6 in (("tcp", False), ("tcp6", True)):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                addr, port = f[1].split(":")
                ip = "::" if v6 and set(addr) == {"0"} else ("0.0.0.0" if set(addr) == {"0"} else
                                                              ".".join(str(int(addr[i:i + 2], 16)) for i in (6, 4, 2, 0))
                                                              if not v6 else addr)
                out.add((ip, int(port, 16)))
    return out


def test_the_ground_listens_only_where_it_is_told(tmp_path):
    """Told nothing, the ground listens nowhere (zenoh's default is a random port on every interface)."""
    from ground.replay import free_port

    base = [sys.executable, "-m", "ground", "run", "--flight-id", "f", "--connect", f"tcp/127.0.0.1:{free_port()}",
            "--no-rrd", "--idle-timeout", "60"]
    port = free_port()
    quiet = subprocess.Popen(base + ["--out", str(tmp_path / "a")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    told = subprocess.Popen(base + ["--out", str(tmp_path / "b"), "--listen", f"tcp/127.0.0.1:{port}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not listening_ports(told.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)  # both opened their sessions by now (same start-up)
        assert quiet.poll() is None and told.poll() is None
        assert listening_ports(told.pid) == {("127.0.0.1", port)}
        assert listening_ports(quiet.pid) == set()
    finally:
        stop_process(quiet)
        stop_process(told)


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make the test certificates")
    d = tmp_path_factory.mktemp("tls")
    subprocess.run(["bash", str(ZENOH_DOCS / "make-certs.sh"), str(d / "certs"), "127.0.0.1"], check=True,
                   capture_output=True)
    (d / "credentials.txt").write_text("drone:change-me-drone\nground:change-me-ground\n")
    return d


def _frames(n: int) -> list[wire.FrameMessage]:
    tel = wire.Telemetry(-28.5, -50.9, 972.0, (1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 3, 0.5, 0)
    return [wire.FrameMessage("tls-flight", "drone-1", i, 1.5e9 + i, tel, 640, 480,
                              np.array([[10, 10, 20, 20]], np.float32), np.array([0.9], np.float32)) for i in range(n)]


def _receive(config: Path, port: int, n: int, timeout: float) -> int:
    try:
        s = transport.open_session(connect=[f"tls/127.0.0.1:{port}"], config_file=str(config))
    except transport.TransportError:
        return 0
    sub = transport.FlightSubscriber(s, "tls-flight")
    got = set()
    t0 = time.monotonic()
    while len(got) < n and time.monotonic() - t0 < timeout:
        m = sub.recv(timeout=0.2)
        if m is not None:
            got.add(m.frame)
    sub.close()
    s.close()
    return len(got)


def test_tls_and_password_let_the_flight_through_and_keep_others_out(certs, monkeypatch):
    from ground.replay import free_port

    monkeypatch.chdir(certs)  # the configs name certs/ and credentials.txt relative to where the node runs
    port = free_port()
    drone = transport.open_session(listen=[f"tls/127.0.0.1:{port}"], config_file=str(ZENOH_DOCS / "onboard-tls.json5"))
    pub = transport.FlightPublisher(drone, "tls-flight", "drone-1")
    try:
        for m in _frames(30):
            pub.publish(m)
        assert _receive(ZENOH_DOCS / "ground-tls.json5", port, 30, 20) == 30
        text = (ZENOH_DOCS / "ground-tls.json5").read_text()
        wrong = certs / "wrong-password.json5"
        wrong.write_text(text.replace("change-me-ground", "not-the-password"))
        no_cert = certs / "no-client-cert.json5"
        no_cert.write_text("\n".join(ln for ln in text.splitlines() if "connect_certificate" not in ln
                                     and "connect_private_key" not in ln))
        for config in (wrong, no_cert):
            assert _receive(config, port, 30, 4) == 0, config.name
        # a plain TCP session cannot speak to the TLS endpoint either
        plain = transport.open_session(connect=[f"tcp/127.0.0.1:{port}"])
        sub = transport.FlightSubscriber(plain, "tls-flight")
        assert sub.recv(timeout=3) is None
        sub.close()
        plain.close()
    finally:
        pub.close()
        drone.close()


def test_a_bad_zenoh_config_is_named(tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(transport.TransportError, match="bad.json5"):
        transport.open_session(config_file=str(bad))
