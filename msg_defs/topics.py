"""The nanostage topic contract, in one place.

Every topic the node graph publishes or a recording holds is a :class:`Topic`: name,
standard message type, units, QoS, rate and content. The recording contract
(``shared/contract/recording.md``) fixes the three hardware topics
(``/stage/reference``, ``/stage/command``, ``/stage/measured``) and the optional ones
(``/experiment/config``, ``/experiment/events``, ``/clock``, ``/stage/truth``,
``/stage/dither``, ``/stage/isolator``); the project adds ``/experiment/trajectory``,
``/stage/correction``, ``/experiment/results``, ``/stage/external_force`` (a known
external force input) and ``/source/channels`` (source columns an importer keeps). ``msg_defs/README.md`` shows the
same table for people; :func:`markdown_table` prints it from this module.

QoS is plain data (:class:`Qos`); the ROS layer turns it into an
``rclpy.qos.QoSProfile`` (:mod:`experiment_runner.ros.qos`), :func:`offered_qos_yaml`
into the ``offered_qos_profiles`` string that rosbag2 (Jazzy, bag version 9) stores on
each MCAP channel. This module imports no ROS package.

Examples
--------
>>> TOPICS["/stage/measured"].msg_type
'sensor_msgs/msg/JointState'
>>> MEASURED.qos.depth, MEASURED.qos.reliability
(1000, 'reliable')
>>> print(offered_qos_yaml(CONFIG).splitlines()[0:4])
['- history: keep_last', '  depth: 1', '  reliability: reliable', '  durability: transient_local']
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "Qos", "Topic", "TOPICS", "CONTRACT_TOPICS",
    "REFERENCE", "COMMAND", "MEASURED", "TRUTH", "DITHER", "ISOLATOR", "CORRECTION", "CLOCK",
    "CONFIG", "EVENTS", "TRAJECTORY", "RESULTS", "SAI_COMMAND", "EXTERNAL_FORCE", "SOURCE_CHANNELS",
    "TABLE", "BEARING", "MOTOR", "PIEZOS", "ISOLATOR_JOINT", "EVENT_KINDS", "FAULT_CAUSES", "COMMAND_KINDS",
    "get_topic", "rosbag2_qos", "offered_qos_yaml", "qos_yaml", "markdown_table",
    "INFINITE_DURATION",
]

# --------------------------------------------------------------------------- joint names
TABLE = "table"
"""Joint name of the table (reference, measured position, truth)."""
BEARING = "bearing"
"""Joint name of the measured bearing displacement (only where a bearing sensor exists)."""
MOTOR = "motor"
"""Joint name of the servo drive on ``/stage/command``."""
PIEZOS = ("piezo_1", "piezo_2")
"""Joint names of the two dither piezos on ``/stage/dither``."""
ISOLATOR_JOINT = "isolator"
"""Joint name on ``/stage/isolator``."""

EVENT_KINDS = ("run_start", "run_end", "trial_start", "trial_end", "abort", "fault")
"""Values of the ``event`` field of an ``/experiment/events`` message."""

FAULT_CAUSES = ("watchdog", "non_finite_input", "diverged", "out_of_travel", "reference_out_of_travel",
                "joined_mid_trial", "restarted", "recording_incomplete")
"""``cause`` of a ``fault`` event: no input within the timeout (the plant holds zero force),
a NaN/inf input, a non-finite or runaway state, the table outside its travel, a reference
outside the travel (refused), a node that joined a trial after its first sample, a node
that restarted mid-run, per-sample messages that never reached the recorder."""

CONTROL_DEPTH = 1000
"""Keep-last depth of the per-sample (lockstep) topics: 0.1 s at the 10 kHz control
rate, so a subscriber (the recorder) that falls that far behind still loses nothing.
Their publishers keep these samples for late joiners too (``transient_local``): a
recorder that discovery matches with a publisher only after the first samples went
out still gets them (see :func:`experiment_runner.ros.qos.subscription_qos`)."""

INFINITE_DURATION = (9223372036, 854775807)
"""``(sec, nsec)`` that rosbag2 writes for an unset (infinite) QoS duration."""


@dataclass(frozen=True)
class Qos:
    """QoS of a topic as plain data (rclpy / rosbag2 policy names, lower case).

    Attributes
    ----------
    reliability : str
        ``"reliable"`` or ``"best_effort"``.
    durability : str
        ``"volatile"`` or ``"transient_local"`` (late joiners get the last ``depth``
        messages).
    depth : int
        Keep-last queue depth [messages].
    history : str
        ``"keep_last"`` or ``"keep_all"``.
    """

    reliability: str = "reliable"
    durability: str = "volatile"
    depth: int = 10
    history: str = "keep_last"

    def __post_init__(self):
        if self.reliability not in ("reliable", "best_effort"):
            raise ValueError(f"reliability {self.reliability!r}: expected 'reliable' or 'best_effort'")
        if self.durability not in ("volatile", "transient_local"):
            raise ValueError(f"durability {self.durability!r}: expected 'volatile' or 'transient_local'")
        if self.history not in ("keep_last", "keep_all"):
            raise ValueError(f"history {self.history!r}: expected 'keep_last' or 'keep_all'")
        if not (isinstance(self.depth, int) and self.depth >= (1 if self.history == "keep_last" else 0)):
            raise ValueError(f"depth {self.depth!r}: expected an int >= 1 for keep_last")


@dataclass(frozen=True)
class Topic:
    """One topic of the contract.

    Attributes
    ----------
    name : str
        Topic name, e.g. ``"/stage/measured"``.
    msg_type : str
        ROS 2 interface type, ``"pkg/msg/Type"`` (standard interfaces only).
    units : str
        SI units of the content.
    qos : Qos
        QoS the publishers offer (subscribers: :func:`experiment_runner.ros.qos.subscription_qos`).
    rate : str
        When it is published.
    description : str
        Content, field by field.
    stream : bool
        A per-sample topic: only a recorder asks for the samples published before it
        joined (a controller that joins late must start from the live sample).
    """

    name: str
    msg_type: str
    units: str
    qos: Qos
    rate: str
    description: str
    stream: bool = False


_LOCKSTEP = Qos("reliable", "transient_local", CONTROL_DEPTH)
_LATCHED = Qos("reliable", "transient_local", 1)

REFERENCE = Topic(
    "/stage/reference", "sensor_msgs/msg/JointState", "m, m/s (rad, rad/s on a rotary stage)", _LOCKSTEP,
    "every control sample",
    'name ["table"], position [x_r], velocity [v_r]: the reference the servo uses at this sample '
    "(including the SAI correction); header.stamp = sample time", stream=True)
COMMAND = Topic(
    "/stage/command", "sensor_msgs/msg/JointState", "N (N·m on a rotary stage)", _LOCKSTEP,
    "every control sample",
    'name ["motor"], effort [F_a]: servo force command sent to the drive for [k, k+1) (or the force '
    "applied, measured: /experiment/config command.kind, see COMMAND_KINDS)", stream=True)
MEASURED = Topic(
    "/stage/measured", "sensor_msgs/msg/JointState", "m (rad on a rotary stage)", _LOCKSTEP,
    "every control sample",
    'name ["table"] or ["table", "bearing"] (bearing only with a bearing displacement sensor), '
    "position as the sensors report it (quantized) at the sample time", stream=True)
TRUTH = Topic(
    "/stage/truth", "sensor_msgs/msg/JointState", "m, m/s, N (rad, rad/s, N·m on a rotary stage)", _LOCKSTEP,
    "every control sample (simulation only)",
    'every body\'s true position and velocity, names "table", "bearing" (first jointed bearing) '
    "and further bodies; effort = friction force on each bearing where known (may be empty)", stream=True)
DITHER = Topic(
    "/stage/dither", "sensor_msgs/msg/JointState", "N", _LOCKSTEP,
    "every control sample (VAN stages)",
    'name ["piezo_1", "piezo_2"], effort = dither forces applied over [k, k+1)', stream=True)
ISOLATOR = Topic(
    "/stage/isolator", "sensor_msgs/msg/JointState", "1 (dimensionless)", Qos("reliable", "transient_local", 10),
    "on every change (SAI stages), and once at start",
    'name ["isolator"], position [1.0] compliant (lock released) or [0.0] stiff; '
    "applies from the sample of its stamp on")
CORRECTION = Topic(
    "/stage/correction", "std_msgs/msg/Float64MultiArray", "m", _LATCHED,
    "once per ILC iteration (before the trial that uses it)",
    "SAI Step II learned reference correction: data[j] is added to the reference at the j-th "
    'sample after each compliant->stiff switch (j = 0 at the first stiff sample); one dimension, '
    'label \'sample:{"iteration": i, "rate": Hz}\', size = number of samples')
CLOCK = Topic(
    "/clock", "rosgraph_msgs/msg/Clock", "ns (builtin_interfaces/Time)", _LOCKSTEP,
    "every control sample",
    "stage time (simulated time in simulation); reliable, not the usual best-effort, so the "
    "lockstep graph is deterministic", stream=True)
CONFIG = Topic(
    "/experiment/config", "std_msgs/msg/String", "SI (text)", _LATCHED,
    "once, first",
    "YAML of the run's configuration (preset, experiment, seeds)")
EVENTS = Topic(
    "/experiment/events", "std_msgs/msg/String", "stamp_ns ns, window_m m, target_m m", Qos("reliable", "volatile", 1000),
    "per event",
    "one JSON object per event: event (run_start|run_end|trial_start|trial_end|abort|fault), "
    "trial (int, 0-based, null for run events), case (str), step_index (int, index of the "
    "step in the case's step sequence, null if none), stamp_ns (int, stage time of the event "
    "[ns] = log time: first sample of the trial for trial_start, last sample for trial_end), "
    "window_m (float, half-width of the settling band [m], null if none), reason (str, why "
    "for abort/fault, else null), node (str, publishing node); optional target_m (float, "
    "position the trial settles at [m]) and settle_start_ns (int, stage time the reference "
    "reaches the target [ns]); readers ignore other keys")
TRAJECTORY = Topic(
    "/experiment/trajectory", "std_msgs/msg/Float64MultiArray", "m, m/s", Qos("reliable", "transient_local", 10),
    "once per trial, before it starts",
    "the whole reference of a trial: dim[0] label \"signal:x_ref,v_ref\" size 2 stride 2N, "
    'dim[1] label \'sample:{"trial": i, "case": "...", "start": k0, "rate": Hz}\' size N '
    "stride N, data_offset 0; data = x_ref[0..N-1] then v_ref[0..N-1]; sample j applies at "
    "control sample k0 + j of the run")
RESULTS = Topic(
    "/experiment/results", "std_msgs/msg/String", "s, m", Qos("reliable", "volatile", 1000),
    "once per trial, at its end",
    "one JSON object per trial: trial, case, settling_time_s, rms_in_position_m, "
    "peak_tracking_error_m, rms_tracking_error_m (null = not settled / not defined), "
    "target_m, settle_start_s, node")

EXTERNAL_FORCE = Topic(
    "/stage/external_force", "sensor_msgs/msg/JointState", "N (N·m on a rotary stage)", _LOCKSTEP,
    "every control sample (only where a known external force acts)",
    'name ["table"], effort [F_e]: a known external force on the table (a shaker, a calibrated load, '
    "a test pulse; not the drive's force, which is /stage/command), +x, applied over [k, k+1); "
    "a recording without this topic had none", stream=True)
SOURCE_CHANNELS = Topic(
    "/source/channels", "sensor_msgs/msg/JointState", "the source file's (as the mapping states them in /experiment/config)",
    _LOCKSTEP, "every control sample (imported recordings that keep extra columns)",
    "name = the source file's column names, position = their values as in the file, unscaled; "
    "kept by nanostage convert (mapping key extra) for the reader's reference, not used by any tool",
    stream=True)

TOPICS: dict[str, Topic] = {t.name: t for t in (
    REFERENCE, COMMAND, MEASURED, TRUTH, DITHER, ISOLATOR, CORRECTION, CLOCK,
    CONFIG, EVENTS, TRAJECTORY, RESULTS, EXTERNAL_FORCE, SOURCE_CHANNELS)}
"""Every topic of the contract, by name."""

CONTRACT_TOPICS = (REFERENCE.name, COMMAND.name, MEASURED.name)
"""The topics every recording has (what a hardware rig can give)."""

COMMAND_KINDS = {
    "drive": "a command to a drive with a force constant: the force applied may differ from it "
             "(force-constant ratio, delay, saturation)",
    "measured": "the force actually applied, measured (a load cell, a drive's own force estimate): no "
                "force-constant error is possible"}
"""What ``/stage/command`` effort holds, said by ``/experiment/config`` ``command.kind``
(the project's extension of the contract, msg_defs/README.md); absent = ``drive``."""

SAI_COMMAND = Topic(
    "/sai/command", "sensor_msgs/msg/JointState", "1, m", Qos("reliable", "volatile", 1000),
    "every control sample, one sample ahead (SAI stages)",
    'name ["isolator"], position [mode] (1 compliant, 0 stiff), effort [x_correction]: the SAI '
    "manager's mode and Step II reference correction for the sample of its stamp")
"""Internal lockstep topic of the graph: not in :data:`TOPICS`, not recorded."""


def get_topic(topic: Topic | str) -> Topic:
    """The :class:`Topic` for a name (or the topic itself); ``KeyError`` names the known ones."""
    if isinstance(topic, Topic):
        return topic
    try:
        return TOPICS[topic]
    except KeyError:
        raise KeyError(f"{topic!r} is not a contract topic; known: {', '.join(TOPICS)}") from None


def _qos_of(topic) -> Qos:
    return topic if isinstance(topic, Qos) else get_topic(topic).qos


def rosbag2_qos(topic: Topic | Qos | str) -> dict:
    """One offered QoS profile as rosbag2 (bag version 9) serializes it, keys in its order.

    Unset durations (deadline, lifespan, liveliness lease) are infinite, as the graph
    reports them for a default publisher; liveliness ``automatic``.
    """
    q = _qos_of(topic)
    inf = {"sec": INFINITE_DURATION[0], "nsec": INFINITE_DURATION[1]}
    return {"history": q.history, "depth": q.depth, "reliability": q.reliability,
            "durability": q.durability, "deadline": dict(inf), "lifespan": dict(inf),
            "liveliness": "automatic", "liveliness_lease_duration": dict(inf),
            "avoid_ros_namespace_conventions": False}


def _scalar(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def qos_yaml(profiles) -> str:
    """Block YAML of a list of profile dicts, laid out as yaml-cpp (rosbag2) dumps it.

    >>> print(qos_yaml([{"depth": 5, "deadline": {"sec": 1, "nsec": 0}}]))
    - depth: 5
      deadline:
        sec: 1
        nsec: 0
    """
    lines = []
    for prof in profiles:
        first = True
        for key, val in prof.items():
            lead = "- " if first else "  "
            first = False
            if isinstance(val, dict):
                lines.append(f"{lead}{key}:")
                lines.extend(f"    {k}: {_scalar(v)}" for k, v in val.items())
            else:
                lines.append(f"{lead}{key}: {_scalar(val)}")
    return "\n".join(lines)


def offered_qos_yaml(topic: Topic | Qos | str) -> str:
    """The ``offered_qos_profiles`` channel metadata string for a topic (one profile)."""
    return qos_yaml([rosbag2_qos(topic)])


def markdown_table() -> str:
    """The topic table as Markdown (what ``msg_defs/README.md`` shows)."""
    rows = ["| topic | type | units | QoS | rate | content |", "|---|---|---|---|---|---|"]
    for t in TOPICS.values():
        q = t.qos
        qos = f"{q.reliability}, {q.durability}, {q.history} {q.depth}"
        rows.append(f"| `{t.name}` | `{t.msg_type}` | {t.units} | {qos} | {t.rate} | "
                    f"{t.description.replace('|', '&#124;')} |")
    return "\n".join(rows)
