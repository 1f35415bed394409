"""What the test modules share: the markers' rules, ROS domains, the graph harness, the shared data.

Markers (registered in ``setup.cfg``; ``--strict-markers`` refuses any other):

* ``slow`` -- more than ~3 s. The fast tier of the edit-test loop is ``pytest -m "not slow"``.
* ``ros`` -- starts DDS: a node process, a ROS graph, an rclpy context. A test that uses the
  graph fixtures below gets it by itself; a test without it that makes an rclpy context or
  starts a node process fails, naming the marker (:func:`_dds_only_with_the_ros_marker`).
* ``dask`` -- starts a Dask cluster (a test using :func:`dask_cluster` gets it by itself).
* ``realdata`` -- reads ``../shared`` (the real data sets, the independent simulator); a test
  using :func:`shared_data` or :func:`shared_file` gets it by itself. When the folder or file is
  missing the test is skipped with the path(s) looked in.

``ros`` and ``dask`` tests are ``slow`` too (added here): the fast tier starts neither DDS nor Dask.
The core suite, without DDS, Dask or the shared data: ``pytest -m "not ros and not dask and not realdata"``.

ROS domains: each graph a test starts runs on a domain of its own, leased from 101..232 (outside
the default 42, the 20..89 of ``nanostage campaign --graph`` and the 1..100 of ``nanostage bench``)
with a lock file held while it runs (:func:`lease_domain`), so graphs of tests running at the same
time -- pytest-xdist workers, or another checkout's suite on the same machine -- never share a domain.

The graph harness is :class:`experiment_runner.ros.launch.NodeProcesses` (the nodes as processes,
as ``nanostage graph --processes`` starts them), made by the :func:`node_graph` fixture on a leased
domain and stopped after the test whatever happens, and :class:`Listener`, an rclpy node in this
process that hears the graph's events (the :func:`listener` fixture).

Real records are diagnosed once per session (:func:`emps_diagnosis`).

Parallel runs: the README's test command runs the suite on every core (``pytest -n auto --dist
loadgroup``, pytest-xdist). The tests sharing a session fixture that is expensive to make (the EMPS
diagnosis, the Dask cluster) are one group each, run by one worker; the longest work is handed out
first (:func:`_start_order`). Domains are leased across processes (above), outputs go to each
test's ``tmp_path``: a test's result never depends on which worker runs it or what runs beside it.

The suite keeps its compiled modules (Python's bytecode, pytest's assertion-rewritten test
modules) in the git-ignored ``__pycache__`` folders even where ``PYTHONDONTWRITEBYTECODE`` is set:
without them every run compiles them all again, half of the fast tier's collection time.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

sys.dont_write_bytecode = False

GRAPH_TIMEOUT = 90.0
"""Bound of every wait on a graph [s]: a whole run, start-up included, on a loaded 2-core machine."""

DOMAINS = range(101, 233)
"""ROS domains leased to tests (the Fast DDS port mapping ends at 232)."""
_LOCKS = Path(tempfile.gettempdir()) / "nanostage-test-ros-domains"

# fixtures that mean a marker: a test using one (directly or through another fixture) gets it
_MARKED_BY_FIXTURE = {"ros": ("ros_domain", "ros_domains", "listener", "node_graph"),
                      "dask": ("dask_cluster",),
                      "realdata": ("shared_data", "shared_file")}
_ALSO_SLOW = ("ros", "dask")
_ONE_WORKER = {"emps_diagnosis", "dask_cluster"}
"""Session fixtures made once per suite: under ``pytest -n`` (``--dist loadgroup``) the tests using
one run on one worker (an ``xdist_group`` of the fixture's name), so it is not made once per worker."""


# =========================================================================== markers
@pytest.hookimpl(tryfirst=True)     # before pytest-xdist's, which turns the xdist_group marks into groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        names = set(getattr(item, "fixturenames", ()))
        for marker, fixtures in _MARKED_BY_FIXTURE.items():
            if item.get_closest_marker(marker) is None and names.intersection(fixtures):
                item.add_marker(getattr(pytest.mark, marker))
        if item.get_closest_marker("slow") is None and any(item.get_closest_marker(m) for m in _ALSO_SLOW):
            item.add_marker(pytest.mark.slow)
        for fixture in _ONE_WORKER.intersection(names):
            item.add_marker(pytest.mark.xdist_group(fixture))
    items.sort(key=_start_order)


def _start_order(item) -> int:
    """Longest work first, so that ``pytest -n`` (``--dist loadgroup``) ends its workers together:
    the tests sharing the EMPS diagnosis (one group, minutes), then the other slow tests, then the
    fast tier (a stable sort: within each rank, the collected order)."""
    if "emps_diagnosis" in getattr(item, "fixturenames", ()):
        return 0
    return 1 if item.get_closest_marker("slow") is not None else 2


@pytest.fixture(autouse=True)
def _dds_only_with_the_ros_marker(request, monkeypatch):
    """A test without the ``ros`` marker that makes an rclpy context or starts a node process fails,
    naming the marker (so the fast tier and the core suite stay free of DDS)."""
    if request.node.get_closest_marker("ros") is not None:
        yield
        return
    from experiment_runner.ros.nodes import NODE_NAMES      # no rclpy import

    def refuse(what):
        raise AssertionError(f"{request.node.nodeid} {what} but is not marked @pytest.mark.ros")

    try:
        import rclpy.context
    except ImportError:                                      # no ROS here: nothing can start DDS in-process
        pass
    else:
        def init(self, *args, **kwargs):
            refuse("initialises an rclpy context")
        monkeypatch.setattr(rclpy.context.Context, "init", init)

    popen_init = subprocess.Popen.__init__

    def popen(self, args, *rest, **kwargs):
        argv = [args] if isinstance(args, (str, os.PathLike)) else list(args)
        if argv and Path(str(argv[0])).name in NODE_NAMES:
            refuse(f"starts the node process {argv[0]}")
        popen_init(self, args, *rest, **kwargs)

    monkeypatch.setattr(subprocess.Popen, "__init__", popen)
    yield


# =========================================================================== ROS domains
@contextlib.contextmanager
def lease_domain():
    """A ROS domain of :data:`DOMAINS` no other leaser holds (lock file held until the block ends)."""
    _LOCKS.mkdir(exist_ok=True)
    start = os.getpid() % len(DOMAINS)
    for k in range(len(DOMAINS)):
        domain = DOMAINS[(start + k) % len(DOMAINS)]
        f = open(_LOCKS / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        try:
            yield domain
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
            f.close()
        return
    raise RuntimeError(f"every ROS domain of {DOMAINS.start}..{DOMAINS.stop - 1} is leased (lock files in {_LOCKS})")


@pytest.fixture
def ros_domains():
    """``ros_domains()``: another leased domain at each call, all held until the test ends."""
    with contextlib.ExitStack() as stack:
        yield lambda: stack.enter_context(lease_domain())


@pytest.fixture
def ros_domain(ros_domains):
    """A domain leased for this test."""
    return ros_domains()


@contextlib.contextmanager
def ros_environment(domain: int):
    """This process's environment set to the isolated ``domain`` (restored afterwards)."""
    from experiment_runner.ros.run import isolate
    saved = dict(os.environ)
    isolate(domain)
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


# =========================================================================== the graph harness
class Listener:
    """An rclpy node in this process (own context) on a graph's domain: hears
    /experiment/events and counts /stage/command messages, and can call parameter services. It
    also subscribes to /experiment/trajectory, so a sequencer told to wait for one more subscriber
    (``wait_for_nodes``) starts only once the listener is matched: no event is missed."""

    def __init__(self, domain: int, defer_trajectory: bool = False):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        from experiment_runner.ros.qos import qos_profile
        from msg_defs import convert
        from msg_defs.topics import COMMAND, EVENTS
        with ros_environment(domain):
            self.ctx = Context()
            rclpy.init(context=self.ctx, domain_id=domain)
            self.node = Node("test_graph_listener", context=self.ctx)
        self.events: list[dict] = []
        self.sub_events = self.node.create_subscription(
            String, EVENTS.name, lambda m: self.events.append(convert.parse_event(m.data)), qos_profile(EVENTS))
        self.commands = 0                                    # /stage/command messages heard
        self.sub_command = self.node.create_subscription(JointState, COMMAND.name, self._command,
                                                         qos_profile(COMMAND))
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        if not defer_trajectory:
            self._join()

    def _join(self):
        from std_msgs.msg import Float64MultiArray

        from experiment_runner.ros.qos import qos_profile
        from msg_defs.topics import TRAJECTORY
        self.node.create_subscription(Float64MultiArray, TRAJECTORY.name, lambda m: None, qos_profile(TRAJECTORY))

    def join_when_matched(self, event_publishers: int, timeout: float = 30.0) -> None:
        """Subscribe to /experiment/trajectory (what the sequencer counts) only once this node's
        command and event subscriptions are matched with the graph's publishers: discovery
        matches each pair of endpoints on its own, and a short run could end before the
        listener hears it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and (self.sub_command.get_publisher_count() < 1
                                                or self.sub_events.get_publisher_count() < event_publishers):
            self.ex.spin_once(timeout_sec=0.02)
        self._join()

    def _command(self, msg):
        self.commands += 1

    def wait_for(self, predicate, timeout: float, alive=None) -> bool:
        """Spin until ``predicate(events)`` (True) or ``timeout`` or ``alive()`` is False."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self.events):
                return True
            if alive is not None and not alive():
                return predicate(self.events)
            self.ex.spin_once(timeout_sec=0.02)
        return predicate(self.events)

    def call(self, request, attempts: int = 4, timeout: float = 5.0):
        """``request()`` (sends a service request, returns its future) until answered. A service
        that discovery shows may not yet have matched this client's response reader (a ROS 2
        race): the answer to the first request can be lost, so it is asked again. All calls here
        are idempotent (get, or set to the same value)."""
        for _ in range(attempts):
            future = request()
            self.ex.spin_until_future_complete(future, timeout_sec=timeout)
            if future.done():
                return future.result()
        raise AssertionError(f"parameter service did not answer {attempts} requests of {timeout} s")

    def close(self):
        import rclpy
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


@pytest.fixture
def listener():
    """``listener(domain, defer_trajectory=False)``: a :class:`Listener`, closed after the test."""
    made = []

    def make(domain: int, **kw) -> Listener:
        made.append(Listener(domain, **kw))
        return made[-1]
    yield make
    for lst in made:
        lst.close()


@pytest.fixture
def node_graph(tmp_path):
    """``node_graph(experiment, domain, **kw)``: the node processes of one run
    (:class:`~experiment_runner.ros.launch.NodeProcesses`, recording to ``tmp_path/run``, each
    node's stderr in ``tmp_path/<node>.stderr``) on ``domain`` with localhost-only discovery;
    every node still running is stopped after the test (a failed test leaves nothing running)."""
    from experiment_runner.ros.launch import NodeProcesses
    from experiment_runner.ros.run import domain_env
    made = []

    def make(experiment, domain: int, **kw) -> NodeProcesses:
        kw.setdefault("out", tmp_path / "run")
        kw.setdefault("stderr_dir", tmp_path)
        made.append(NodeProcesses(str(experiment), env=domain_env(domain), **kw))
        return made[-1]
    yield make
    for g in made:
        if any(p.poll() is None for p in g.procs.values()):
            g.stop()


# =========================================================================== Dask
@pytest.fixture(scope="session")
def dask_cluster():
    """One Dask ``LocalCluster`` of two single-threaded worker processes for the whole session."""
    import logging

    from distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        yield cluster


# =========================================================================== shared data
@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real data folder (``../shared/data``,
    :func:`experiment_runner.apps.diagnosis.datasets.data_root`); the test is skipped, naming every
    place looked in, when it is missing."""
    from experiment_runner.apps.diagnosis.datasets import DataMissing, data_root
    try:
        return data_root()
    except DataMissing as err:
        pytest.skip(f"real data missing: {err}")


@pytest.fixture(scope="session")
def shared_file(shared_data):
    """``shared_file("emps/DATA_EMPS.mat")``: that file of the real data folder; the test is
    skipped, naming the path, when it is not there."""
    def get(relative: str) -> Path:
        path = shared_data / relative
        if not path.is_file():
            pytest.skip(f"real data missing: {path} does not exist")
        return path
    return get


@pytest.fixture(scope="session")
def emps_diagnosis(shared_data, shared_file, tmp_path_factory) -> dict:
    """The EMPS record diagnosed once for the whole suite, as ``nanostage realdata`` does it
    (:func:`experiment_runner.apps.diagnosis.emps.run_emps`: converted by ``nanostage convert emps``,
    diagnosed with ``nanostage diagnose``'s defaults from the shipped nominal, the published-structure
    fits, closed-loop replays; no plots), without the wall-clock budget: the answer must not depend
    on the machine's load (how long it takes is ``nanostage bench``'s ``diagnose_seconds_emps``).

    ``{"summary": run_emps's result, "recording": the converted recording, "diagnosis": the folder
    of report.json and improved_preset.yaml}``."""
    from experiment_runner.apps.diagnosis import emps as R
    shared_file("emps/DATA_EMPS.mat")
    out = tmp_path_factory.mktemp("emps")
    summary = R.run_emps(shared_data, out, structure_check=True, plots=False, max_seconds=None)
    return {"summary": summary, "recording": out / "recording", "diagnosis": out / "diagnosis"}
