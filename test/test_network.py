"""The ROS graph reaches no other host unless it is opened (``docs/security.md``).

The real thing: ``nanostage graph`` (one process per node, and all in one process),
``nanostage replay`` and a node started by hand run from a shell that sets no ROS
variable, and every UDP / TCP socket of their processes is read from ``/proc`` while they
run (``/proc/<pid>/fd`` -> socket inodes -> ``/proc/<pid>/net/{udp,udp6,tcp,tcp6}``).
Each run is on a ROS domain leased to it (``conftest.lease_domain``).
"""
from __future__ import annotations

import ipaddress
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import lease_domain

from experiment_runner.ros.run import (GRAPH_DEFAULTS, LOOPBACK_PROFILE, apply_graph_defaults, domain_env,
                                       loopback_env)

BIN = Path(sys.executable).parent
RUN_TIMEOUT = 180.0                      # s: a whole graph run, start-up included (a loaded machine)


def _user_env() -> dict:
    """This environment without any ROS or Fast DDS setting: a user's plain shell."""
    return {k: v for k, v in os.environ.items()
            if not k.startswith(("ROS_", "FASTRTPS_", "FASTDDS_", "RMW_")) and k != "SKIP_DEFAULT_XML_FILE"}


def _address(text: str) -> tuple[ipaddress._BaseAddress, int]:
    """``0100007F:1F90`` (``/proc/net``: the address in host byte order, 32-bit words) -> (address, port)."""
    hexaddr, port = text.split(":")
    raw = bytes.fromhex(hexaddr)
    raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    addr = ipaddress.ip_address(raw)
    if addr.version == 6 and addr.ipv4_mapped:
        addr = addr.ipv4_mapped
    return addr, int(port, 16)


def sockets(pid: int) -> set[tuple[str, str, int]]:
    """``(protocol, local address, port)`` of every UDP / TCP socket process ``pid`` holds."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:                 # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = set()
    for proto in ("udp", "udp6", "tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{proto}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[9] in inodes:
                addr, port = _address(fields[1])
                found.add((proto, str(addr), port))
    return found


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return out


def _name(pid: int) -> str:
    argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    return " ".join(Path(a.decode()).name for a in argv[:2] if a)


def watch(args, env, timeout=RUN_TIMEOUT) -> tuple[subprocess.CompletedProcess, dict]:
    """Run ``args`` and list the sockets of it and every process it starts, every 0.2 s until
    it ends: ``(completed process, {process name: sockets})``."""
    seen: dict[str, set] = {}
    with subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        deadline = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < deadline:
            for pid in _tree(proc.pid):
                try:
                    seen.setdefault(_name(pid), set()).update(sockets(pid))
                except OSError:         # it ended meanwhile
                    pass
            time.sleep(0.2)
        if proc.poll() is None:
            proc.kill()
        out, err = proc.communicate()
    return subprocess.CompletedProcess(args, proc.returncode, out, err), seen


def not_loopback(seen: dict) -> dict:
    return {name: sorted(s for s in socks if not ipaddress.ip_address(s[1]).is_loopback)
            for name, socks in seen.items() if any(not ipaddress.ip_address(s[1]).is_loopback for s in socks)}


NODES = ("plant_sim", "servo_controller", "dither_generator", "sai_manager", "recorder", "experiment_sequencer")


@pytest.fixture(scope="module")
def processes_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("graph_processes")
    with lease_domain() as domain:
        run, seen = watch([str(BIN / "nanostage"), "graph", "fi_p2p_5um", "--processes", "--out", str(out),
                           "--domain-id", str(domain)], _user_env())
    return run, seen, out


@pytest.mark.ros
def test_a_graph_of_node_processes_has_every_socket_on_loopback(processes_run):
    run, seen, _ = processes_run
    assert run.returncode == 0, run.stderr
    for node in NODES:                               # every node was seen with its sockets
        assert any(name.endswith(node) and socks for name, socks in seen.items()), (node, seen)
    assert not_loopback(seen) == {}, seen


@pytest.mark.ros
def test_a_graph_in_one_process_has_every_socket_on_loopback(tmp_path, ros_domain):
    run, seen = watch([str(BIN / "nanostage"), "graph", "fi_p2p_5um", "--out", str(tmp_path),
                       "--domain-id", str(ros_domain)], _user_env())
    assert run.returncode == 0, run.stderr
    assert any(socks for socks in seen.values()), seen
    assert not_loopback(seen) == {}, seen


@pytest.mark.ros
def test_replay_has_every_socket_on_loopback(processes_run, ros_domain):
    _, _, out = processes_run
    run, seen = watch([str(BIN / "nanostage"), "replay", str(out / "run.mcap"), "--rate", "2",
                       "--domain-id", str(ros_domain)], _user_env())
    assert run.returncode == 0, run.stderr
    assert any(socks for socks in seen.values()), seen
    assert not_loopback(seen) == {}, seen


def _hand_started(env: dict, settle: float = 1.5) -> set:
    """Start ``plant_sim`` by hand with ``env``; its sockets once it has had them ``settle`` s
    and is spinning (it said "ready": its kernels loaded, so SIGTERM is a clean stop, where
    during the load it ends the process at once as ``launch.STARTING``)."""
    proc = subprocess.Popen([str(BIN / "plant_sim")], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    lines, ready = [], threading.Event()

    def read():
        for line in proc.stderr:
            lines.append(line)
            if ": ready (kernels loaded" in line:
                ready.set()
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        seen, first = set(), None
        deadline = time.monotonic() + RUN_TIMEOUT
        while time.monotonic() < deadline and proc.poll() is None and (
                first is None or time.monotonic() < first + settle or not ready.is_set()):
            seen |= sockets(proc.pid)
            if seen and first is None:
                first = time.monotonic()
            time.sleep(0.1)
        assert proc.poll() is None, "".join(lines)
        assert ready.is_set(), f"not ready within {RUN_TIMEOUT} s: {''.join(lines)}"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        reader.join(timeout=10)
    err = "".join(lines)
    assert proc.returncode == 0 and "Traceback" not in err, err
    return seen


@pytest.mark.ros
def test_a_node_started_by_hand_has_its_sockets_on_loopback_unless_the_graph_is_opened(ros_domains):
    seen = _hand_started(dict(_user_env(), ROS_DOMAIN_ID=str(ros_domains())))
    assert seen and not_loopback({"plant_sim": seen}) == {}, seen
    # opened the documented way: the middleware's own settings, sockets on every interface
    opened = ros_domains()
    seen = _hand_started(dict(_user_env(), ROS_DOMAIN_ID=str(opened), ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"))
    assert ("udp", "0.0.0.0", 7400 + 250 * opened) in seen, seen      # the multicast discovery port


# --------------------------------------------------------------------------- which settings apply when
LOOPBACK = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT", "FASTRTPS_DEFAULT_PROFILES_FILE": str(LOOPBACK_PROFILE),
            "SKIP_DEFAULT_XML_FILE": "1"}


def test_a_local_graph_uses_the_loopback_profile_and_an_opened_one_does_not():
    env = {}                                        # nothing set: local (GRAPH_DEFAULTS), on loopback
    assert GRAPH_DEFAULTS["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert apply_graph_defaults(env) == {"ROS_DOMAIN_ID": "42", **LOOPBACK} and env == {"ROS_DOMAIN_ID": "42", **LOOPBACK}
    for local in ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, {"ROS_LOCALHOST_ONLY": "1"},
                  {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}):
        env = dict(local, ROS_DOMAIN_ID="7")
        assert apply_graph_defaults(env) == LOOPBACK, local
        kept = {k: v for k, v in local.items() if k != "ROS_LOCALHOST_ONLY"}     # deprecated; replaced
        assert env == {**kept, "ROS_DOMAIN_ID": "7", **LOOPBACK}, local
    for opened in ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, {"ROS_LOCALHOST_ONLY": "0"},
                   {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"},
                   {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": "192.168.10.20"},
                   {"ROS_DISCOVERY_SERVER": "192.168.10.20:11811"},
                   {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/rig_profile.xml"},
                   {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}):
        env = dict(opened, ROS_DOMAIN_ID="7")
        chosen = apply_graph_defaults(env)
        assert loopback_env(env) == {} and "FASTRTPS_DEFAULT_PROFILES_FILE" not in chosen, opened
        assert {k: env[k] for k in opened} == opened                      # what the user set stays
    # the simulation graph is local whatever the shell says
    env = domain_env(7)
    for name, value in LOOPBACK.items():
        assert env[name] == value


def test_the_simulation_graph_is_local_whatever_the_shell_says(monkeypatch):
    for name, value in {"ROS_STATIC_PEERS": "192.168.10.20", "ROS_DISCOVERY_SERVER": "192.168.10.20:11811",
                        "FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/rig_profile.xml", "ROS_LOCALHOST_ONLY": "0",
                        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}.items():
        monkeypatch.setenv(name, value)
    env = domain_env(9)
    assert env["ROS_DOMAIN_ID"] == "9" and {k: env[k] for k in LOOPBACK} == LOOPBACK
    assert not {"ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY"} & set(env)


def test_the_loopback_profile_binds_udp_to_127_0_0_1_only():
    import xml.etree.ElementTree as ET
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(LOOPBACK_PROFILE).getroot()
    udp = [t for t in root.iterfind(".//f:transport_descriptor", ns) if t.findtext("f:type", namespaces=ns) == "UDPv4"]
    assert [i.get("name") for t in udp for i in t.iterfind(".//f:allowlist/f:interface", ns)] == ["127.0.0.1"]
    participant = root.find(".//f:participant", ns)
    assert participant.get("is_default_profile") == "true"
    assert participant.findtext(".//f:useBuiltinTransports", namespaces=ns) == "false"
    locators = {e.tag.split("}")[1]: [a.text for a in e.iterfind(".//f:address", ns)]
                for e in participant.iter() if e.tag.endswith("LocatorList") or e.tag.endswith("PeersList")}
    assert locators == {"metatrafficUnicastLocatorList": ["127.0.0.1"], "initialPeersList": ["127.0.0.1"],
                        "defaultUnicastLocatorList": ["127.0.0.1"]}
