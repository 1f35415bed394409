"""Running nodes: the graph's environment, the executor, and ``main`` of a node executable.

* :func:`domain_env` / :func:`apply_graph_defaults`: an explicit ROS domain and
  localhost-only discovery, every socket on 127.0.0.1 (:func:`loopback_env`), unless the
  environment says otherwise (``docs/security.md`` tells how to open the graph);
* :func:`check_params_files`: a node's ``--params-file`` read with the project's YAML loader;
* :func:`make_executor`: rclpy's C++ ``EventsExecutor`` (default) or the
  ``SingleThreadedExecutor``;
* :func:`run_node`: init, spin, clean up -- every node module's ``main`` is one call of it.
"""
from __future__ import annotations

import faulthandler
import os
import signal
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions
from stage_sim.validation import ConfigError, load_yaml

__all__ = ["domain_env", "isolate", "GRAPH_DEFAULTS", "LOOPBACK_PROFILE", "loopback_env", "apply_graph_defaults",
           "DOMAIN_IDS", "check_domain_id", "executor_kind", "make_executor", "run_node", "params_source",
           "check_params_files", "EXIT_GRACE_S", "DRAIN_MIN_S", "DRAIN_MAX_S"]


DOMAIN_IDS = range(0, 233)
"""ROS domain IDs a graph can use here: Fast DDS derives its UDP ports from the domain, and
above 232 they leave the port range (the participant cannot be created: the process ends)."""


def check_domain_id(value=None, environ=os.environ) -> int:
    """The ROS domain a run will use (``value``, else ``ROS_DOMAIN_ID``, else 42), checked:
    ``ValueError`` naming the value, where it came from and what is allowed.

    >>> check_domain_id(7), check_domain_id(None, {"ROS_DOMAIN_ID": "12"}), check_domain_id(None, {})
    (7, 12, 42)
    >>> check_domain_id(300)
    Traceback (most recent call last):
    ...
    ValueError: ROS domain ID (--domain-id): got 300; expected an integer from 0 to 232
    """
    source = "--domain-id" if value is not None else "environment variable ROS_DOMAIN_ID"
    if value is None:
        value = environ.get("ROS_DOMAIN_ID", GRAPH_DEFAULTS["ROS_DOMAIN_ID"])
    try:
        domain = int(str(value).strip())
    except ValueError:
        domain = None
    if domain is None or domain not in DOMAIN_IDS:
        raise ValueError(f"ROS domain ID ({source}): got {value!r}; expected an integer from "
                         f"{DOMAIN_IDS.start} to {DOMAIN_IDS.stop - 1}")
    return domain


def domain_env(domain_id: int | None = None) -> dict:
    """Environment for an isolated graph (``nanostage graph``, its tests): explicit domain,
    localhost-only discovery whatever the environment says (``ROS_LOCALHOST_ONLY``,
    ``ROS_STATIC_PEERS``, ``ROS_DISCOVERY_SERVER`` and a Fast DDS profile of its own are
    dropped), every socket on 127.0.0.1 (:func:`loopback_env`).

    >>> env = domain_env(7)
    >>> env["ROS_DOMAIN_ID"], env["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(LOOPBACK_PROFILE)
    ('7', True)
    """
    env = dict(os.environ)
    for name in ("ROS_LOCALHOST_ONLY", *OPENING_VARIABLES):
        env.pop(name, None)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_DOMAIN_ID", GRAPH_DEFAULTS["ROS_DOMAIN_ID"])
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.update(loopback_env(env))
    return env


def isolate(domain_id: int | None = None, environ=os.environ) -> None:
    """Make ``environ`` (this process's environment) :func:`domain_env`'s, removals included."""
    env = domain_env(domain_id)
    for name in set(environ) - set(env):
        del environ[name]
    environ.update(env)


GRAPH_DEFAULTS = {"ROS_DOMAIN_ID": "42", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
"""What a node started by hand gets unless its environment says otherwise: an explicit
domain and localhost-only discovery (``docs/security.md`` tells how to open the graph)."""

LOOPBACK_PROFILE = Path(__file__).with_name("fastdds_loopback.xml")
"""Fast DDS participant profile of a localhost-only graph: shared memory, and UDP only on
127.0.0.1 (sockets bound there, discovery by unicast to 127.0.0.1, no multicast)."""

OPENING_VARIABLES = ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "FASTRTPS_DEFAULT_PROFILES_FILE")
"""Settings with which a user reaches beyond this machine or configures Fast DDS: where one is
set, a node's graph is not confined to loopback (:func:`loopback_env`)."""


def loopback_env(environ=os.environ) -> dict:
    """The variables that confine a localhost-only graph to the loopback interface ({} where
    ``environ`` does not ask for localhost-only discovery, names a peer, a discovery server or a
    Fast DDS profile of its own, or another middleware than Fast DDS).

    rmw_fastrtps_cpp's own ``LOCALHOST`` mode only discovers on 127.0.0.1: it adds a UDP
    transport whose sockets listen on every interface. Instead the discovery range becomes
    ``SYSTEM_DEFAULT`` (the middleware's settings) and the middleware's settings are
    :data:`LOOPBACK_PROFILE`; ``SKIP_DEFAULT_XML_FILE`` keeps Fast DDS from also loading a
    ``DEFAULT_FASTRTPS_PROFILES.xml`` of the working directory over it. Fast DDS reads its
    profiles once per process, when the first participant is made: set these before it.

    >>> sorted(loopback_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}))
    ['FASTRTPS_DEFAULT_PROFILES_FILE', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'SKIP_DEFAULT_XML_FILE']
    >>> loopback_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    {}
    >>> loopback_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": "192.168.10.20"})
    {}
    """
    scope = environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
    if scope is None and environ.get("ROS_LOCALHOST_ONLY") == "1":
        scope = "LOCALHOST"
    if (scope != "LOCALHOST" or any(environ.get(name) for name in OPENING_VARIABLES)
            or not environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps")):
        return {}
    return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT",
            "FASTRTPS_DEFAULT_PROFILES_FILE": str(LOOPBACK_PROFILE), "SKIP_DEFAULT_XML_FILE": "1"}


def apply_graph_defaults(environ=os.environ) -> dict:
    """Set :data:`GRAPH_DEFAULTS` in ``environ`` where it names neither (``ROS_LOCALHOST_ONLY``
    counts as a discovery choice), then confine a localhost-only graph to loopback
    (:func:`loopback_env`); return what was set.

    >>> env = {}
    >>> apply_graph_defaults(env)["ROS_AUTOMATIC_DISCOVERY_RANGE"], env["ROS_DOMAIN_ID"]
    ('SYSTEM_DEFAULT', '42')
    >>> apply_graph_defaults({"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    {}
    """
    chosen = {}
    if "ROS_DOMAIN_ID" not in environ:
        chosen["ROS_DOMAIN_ID"] = GRAPH_DEFAULTS["ROS_DOMAIN_ID"]
    if "ROS_AUTOMATIC_DISCOVERY_RANGE" not in environ and "ROS_LOCALHOST_ONLY" not in environ:
        chosen["ROS_AUTOMATIC_DISCOVERY_RANGE"] = GRAPH_DEFAULTS["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    environ.update(chosen)
    loopback = loopback_env(environ)
    if loopback:
        environ.pop("ROS_LOCALHOST_ONLY", None)
    environ.update(loopback)
    return {**chosen, **loopback}


def params_files(argv) -> list[str]:
    """The ``--params-file`` arguments of a node's command line."""
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--params-file"]


def params_source(argv) -> str:
    """Where a node's parameters come from, for error messages."""
    files = params_files(argv)
    return f"params file {', '.join(files)}" if files else "command line / defaults"


def check_params_files(argv, node: str = "node") -> None:
    r"""Read every ``--params-file`` of ``argv`` with the project's YAML loader
    (:func:`stage_sim.validation.load_yaml`: safe, duplicate keys refused) before ROS parses
    it: a :class:`~stage_sim.validation.ConfigError` naming ``node``, the file and the line.

    >>> import tempfile
    >>> with tempfile.NamedTemporaryFile("w", suffix=".yaml") as f:
    ...     _ = f.write("plant_sim:\n  ros__parameters:\n    input_timeout: [1.0\n")
    ...     f.flush()
    ...     check_params_files(["--ros-args", "--params-file", f.name], "plant_sim")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    stage_sim.validation.ConfigError: plant_sim (params file ...): not valid YAML at line 4, column 1: ...
    """
    for name in params_files(argv):
        path, source = Path(name), f"{node} (params file {name})"
        if not path.exists():
            raise ConfigError(f"{source}: no such file")
        if not path.is_file():
            raise ConfigError(f"{source}: not a regular file")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"{source}: cannot read it ({err})") from None
        data = load_yaml(text, source)
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: top level must be a mapping of node names, got {type(data).__name__}")


def _rcl_error_text(err) -> str:
    """An ``RCLError`` of ``rclpy.init`` as one line: without rcl's source locations."""
    import re
    text = re.sub(r", at /\S+:\d+", "", str(err))
    return text.removeprefix("failed to initialize rcl: ")


def executor_kind(kind: str | None = None) -> str:
    """``"events"`` (rclpy's C++ ``EventsExecutor``) or ``"single"`` (``SingleThreadedExecutor``):
    ``kind``, else ``NANOSTAGE_EXECUTOR``, else ``"events"`` where rclpy has it."""
    kind = kind or os.environ.get("NANOSTAGE_EXECUTOR") or "events"
    if kind not in ("events", "single"):
        raise ValueError(f"executor {kind!r}: expected 'events' or 'single'")
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor  # noqa: F401
        except ImportError:
            return "single"
    return kind


def make_executor(context=None, kind: str | None = None):
    """The executor the nodes spin in (see :func:`executor_kind`).

    The lockstep graph is callback-bound; the ``EventsExecutor`` dispatches callbacks
    from C++ without rebuilding a wait set for each one (3-5x the callback rate of
    the ``SingleThreadedExecutor``, whose wait set here holds ~100 entities).
    """
    if executor_kind(kind) == "events":
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(context=context)


def spin_for(ex, seconds: float) -> None:
    """Run ``ex``'s callbacks for ``seconds`` (wall clock), or until it is stopped.

    One call for many callbacks: the ``EventsExecutor`` dispatches them in its C++ loop
    (``spin_once`` returns to Python, re-takes its lock and releases the GIL for each one).
    """
    from rclpy.task import Future
    ex.spin_until_future_complete(Future(), timeout_sec=seconds)


EXIT_GRACE_S = 5.0
"""Wall-clock time a node gets, once it is told to stop (SIGINT) or its run is done, to tear
down ROS before it ends itself: DDS teardown must never leave a node hanging. Its own
clean-up (``on_exit``: e.g. closing a recording) always finishes first."""


DRAIN_MIN_S, DRAIN_MAX_S = 0.5, 5.0
"""Shortest and longest time a draining node (the recorder) keeps taking messages after it
is told to stop [s]."""


def run_node(factory, args=None, until=None, on_exit=None, drain=None):
    """``main`` of a node executable: init, spin (until ``until(node)`` is true), clean up.

    Once made, the node loads its compiled kernels
    (:meth:`~experiment_runner.ros.node.StageNode.warm_up`) before it spins, then logs
    ``ready (kernels loaded in X s)``. Ctrl-C / SIGINT ends
    it cleanly (while it still loads them: at once, ended by the signal, as while importing);
    ``on_exit(node)`` runs last (e.g. close a file) and may return the process's exit status.
    Whatever hangs after that, the process ends within :data:`EXIT_GRACE_S` of being stopped.
    ``drain(node)``: on SIGINT / SIGTERM the node keeps spinning while this is true (at most
    :data:`DRAIN_MAX_S`): a recorder that is behind takes the messages already on their way
    before it closes its file.
    """
    faulthandler.register(signal.SIGUSR1, all_threads=True)     # a hung node's stacks, on request
    chosen = apply_graph_defaults()
    # SIGINT / SIGTERM just set ``stop`` (no rclpy signal-handler thread shutting ROS down under
    # a spinning executor): the loop ends within one spin, ROS is torn down from this thread,
    # and a draining node keeps ROS up while it takes what is still on its way
    stop = threading.Event()
    argv = sys.argv if args is None else args
    executable = Path(argv[0]).name if argv else "node"
    try:                                                       # bad ROS arguments: one line, exit 2
        check_params_files(argv, executable)
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except (ValueError, _rclpy.RCLError) as err:
        print(f"error: {err}" if isinstance(err, ValueError) else f"error: {executable}: {_rcl_error_text(err)}",
              file=sys.stderr)
        sys.exit(2)
    starting = {"warm_up": False, "signal": None}      # a signal while the node loads its kernels ends it at once

    def on_signal(sig, frame):
        stop.set()
        if starting["warm_up"]:
            starting["signal"] = sig
            raise KeyboardInterrupt
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    status = [0]
    stopping, cleanup = _exit_guard(rclpy.get_default_context(), status, stop,
                                    EXIT_GRACE_S + (DRAIN_MAX_S if drain else 0.0))
    node = ex = None
    try:
        try:
            node = factory()
            _refuse_unknown_parameters(node)
        except (ValueError, InvalidParameterValueException,
                InvalidParameterTypeException) as err:                 # bad parameter: say which
            print(f"error: {err}", file=sys.stderr)
            if node is not None:
                node.destroy_node()
                node = None
            rclpy.shutdown()
            sys.exit(2)
        if chosen:
            node.get_logger().info(f"graph defaults {chosen} (set them to open the graph: docs/security.md)")
        # the kernels it steps per sample are loaded before the node spins, hence before it joins a
        # run (StageNode.warm_up); discovery goes on meanwhile. Stopped now, it ends at once (still starting)
        starting["warm_up"] = True
        t_warm = time.monotonic()
        node.warm_up()
        starting["warm_up"] = False
        node.get_logger().info(f"ready (kernels loaded in {time.monotonic() - t_warm:.1f} s)")
        ex = make_executor()
        ex.add_node(node)
        while rclpy.ok() and not stop.is_set() and not (until and until(node)):
            spin_for(ex, 0.05)
        if drain is not None:                                      # at least DRAIN_MIN_S: it may just
            t_stop = time.monotonic()                             # have been resumed (SIGCONT)
            while rclpy.ok() and time.monotonic() < t_stop + DRAIN_MAX_S and (
                    time.monotonic() < t_stop + DRAIN_MIN_S or drain(node)):
                ex.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        stopping.set()
        if node is not None:
            if on_exit:
                with cleanup:
                    status[0] = on_exit(node) or 0
            # what must be kept is kept: from here a GIL-free watchdog (a C thread) ends the
            # process should ROS teardown block while holding the GIL (where the Python guard
            # above can no longer run)
            faulthandler.dump_traceback_later(EXIT_GRACE_S + 2.0, exit=True)
            teardown(ex, node)
        if rclpy.ok():
            rclpy.shutdown()
    if starting["signal"] is not None:              # stopped while starting: ended by the signal, as
        signal.signal(starting["signal"], signal.SIG_DFL)      # while importing (launch.STARTING)
        os.kill(os.getpid(), starting["signal"])
    if status[0]:
        sys.exit(status[0])


def teardown(ex, *nodes) -> None:
    """Stop ``ex`` and let go of its entities while the ``nodes`` and the context are alive, then
    destroy the nodes. The other order (nodes destroyed under a live executor, the executor
    dropped later by garbage collection, after ``rclpy.shutdown``) finalises the nodes' QoS
    event handles from the executor's destructor at an arbitrary point; on a loaded machine
    that blocked a plant for good (CI: stuck in ``EventHandler.__exit__`` holding the GIL)."""
    if ex is not None:
        ex.shutdown(timeout_sec=EXIT_GRACE_S)
    for node in nodes:
        node.destroy_node()


def _exit_guard(context, status, stop, grace: float):
    """Start a daemon thread that ends the process (with ``status[0]``) ``grace`` seconds after
    ``context`` is shut down (rclpy's SIGINT handler), ``stop`` is set (ours) or the returned
    event is set, unless it ended by itself; it waits while the returned lock (held by the
    node's own clean-up) is taken."""
    stopping, cleanup = threading.Event(), threading.Lock()

    def guard():
        while not stopping.wait(0.2) and not stop.is_set() and context.ok():
            pass
        time.sleep(grace)
        with cleanup:
            print(f"[run_node] ROS teardown did not finish {grace} s after stop: exiting", file=sys.stderr, flush=True)
            os._exit(status[0])
    threading.Thread(target=guard, name="exit_guard", daemon=True).start()
    return stopping, cleanup


def _refuse_unknown_parameters(node) -> None:
    """``ValueError`` if a params file or ``-p`` sets a parameter the node does not have (a typo
    would otherwise be ignored silently)."""
    unknown = sorted(n for n in node._parameter_overrides
                     if not node.has_parameter(n) and not n.startswith("qos_overrides."))
    if unknown:
        known = ", ".join(sorted(node._parameters))
        lines = [f"  {n}: unknown parameter (got {node._parameter_overrides[n].value!r}); allowed: {known}"
                 for n in unknown]
        raise ValueError(f"{node.get_name()} ({params_source(sys.argv)}): invalid parameters\n" + "\n".join(lines))


