"""Writing a recording: :class:`McapRecorder`, a rosbag2 bag with one MCAP file."""
from __future__ import annotations

import struct
import zlib
from collections import Counter
from functools import lru_cache

from experiment_runner.core import outputs
from experiment_runner.core.recording.mcap import CHUNK_CRC_OFFSET, bag_layout
from msg_defs import convert
from msg_defs.topics import CONFIG, TOPICS, Qos, qos_yaml


@lru_cache(maxsize=None)
def typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=None)
def _writer_classes():
    """rosbags' Writer with its MCAP storage closing (and flushing) chunks by stage time."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.metadata import dump_qos_v9
    from rosbags.rosbag2.storage_mcap import McapWriter

    class ChunkedMcap(McapWriter):
        chunk_ns = 100_000_000
        chunk_bytes = 1 << 20

        def add_connection(self, connection, offered_qos_profiles):
            # the channel's offered_qos_profiles in rosbag2's (yaml-cpp) layout and key order
            qos = qos_yaml(dump_qos_v9(list(connection.ext.offered_qos_profiles)))
            super().add_connection(connection, qos)

        def write(self, connection, timestamp, data):
            super().write(connection, timestamp, data)
            ck = self.chunk
            if ck.msgs and (ck.message_end_time - ck.message_start_time >= self.chunk_ns
                            or ck.bio.tell() >= self.chunk_bytes):
                self.close_chunk()

        def close_chunk(self):
            # rosbags leaves the chunk CRC 0 ("not computed"): write the CRC-32 of the
            # uncompressed records into the chunk record, so readers detect damage
            crc = zlib.crc32(self.chunk.bio.getbuffer())
            start = self.bio.tell()
            super().close_chunk()
            end = self.bio.tell()
            self.bio.seek(start + CHUNK_CRC_OFFSET)
            self.bio.write(struct.pack("<I", crc))
            self.bio.seek(end)
            self.bio.flush()          # a killed process keeps every closed chunk

    class ChunkedWriter(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: ChunkedMcap}

    return ChunkedWriter, StoragePlugin


def _rosbags_qos(q: Qos):
    from rosbags.interfaces import Qos as RQos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    inf = QosTime(9223372036, 854775807)
    return RQos(QosHistory[q.history.upper()], q.depth, QosReliability[q.reliability.upper()],
                QosDurability[q.durability.upper()], inf, inf, QosLiveliness.AUTOMATIC, inf, False)


class McapRecorder:
    """Write a contract recording (rosbag2 bag, MCAP storage) message by message.

    Parameters
    ----------
    path : str or Path
        Bag directory to create (see :func:`bag_layout`); ``self.path`` is the MCAP file.
    config_yaml : str, optional
        YAML of the run's configuration, written first on ``/experiment/config``.
    start_ns : int
        Stage time [ns] of the config message.
    chunk_ns : int
        Close (and flush) a chunk once it spans this much stage time [ns].
    chunk_bytes : int
        ... or once it holds this many bytes (rosbags closes at 1 MiB anyway).
    overwrite : bool
        Replace an existing recording at ``path`` (only nanostage's files in it:
        :mod:`experiment_runner.core.outputs`); otherwise an existing one is refused
        (:class:`~experiment_runner.core.outputs.OutputError`).
    atomic : bool
        Write the bag in a temporary folder beside ``path`` and move it into place on
        :meth:`close` (a run that fails or is interrupted leaves nothing at ``path``: files
        written whole, such as a campaign's or ``synth``'s). Default: written in place, so a
        killed process leaves a file readable up to its last chunk (the ``recorder`` node).

    ``write(topic, stamp_ns, msg)`` takes rclpy messages, rosbags messages or raw CDR
    bytes. Topics of :data:`msg_defs.topics.TOPICS` get their contract type and QoS;
    others need :meth:`add_topic` (or a message, whose type is then used). Use it as a
    context manager, or call :meth:`close`, which writes the index and summary. Not
    thread-safe: call it from one thread (e.g. one recorder node's callbacks).
    """

    def __init__(self, path, config_yaml: str | None = None, *, start_ns: int = 0,
                 chunk_ns: int = 100_000_000, chunk_bytes: int = 1 << 20, overwrite: bool = False,
                 atomic: bool = False):
        self.bag_dir, self.path = bag_layout(path)
        self._install = outputs.replacing_folder(self.bag_dir, overwrite) if atomic else None
        if atomic:
            where = self._install.__enter__()
        else:
            outputs.prepare_recording(self.bag_dir, overwrite)
            where = self.bag_dir
        writer_cls, plugin = _writer_classes()
        self._store = typestore()
        self._conns: dict = {}
        self.counts: Counter = Counter()
        self._closed = False
        self._writer = None
        try:
            self._writer = writer_cls(where, version=9, storage_plugin=plugin.MCAP)
            self._writer.set_custom_data("nanostage_recording_contract", "1")
            self._writer.open()
            if not atomic:
                outputs.record(where, [self.path.name, "metadata.yaml"])
            self._writer.storage.chunk_ns = int(chunk_ns)
            self._writer.storage.chunk_bytes = int(chunk_bytes)
            if config_yaml is not None:
                self.write(CONFIG.name, start_ns, convert.string_msg(self._store, config_yaml))
        except BaseException as err:
            self._finish(err)
            raise

    # ------------------------------------------------------------------ topics
    def add_topic(self, name: str, msg_type: str | None = None, qos: Qos | None = None):
        """Declare a topic (contract topics need nothing; others need ``msg_type``)."""
        topic = TOPICS.get(name)
        if msg_type is None:
            if topic is None:
                raise KeyError(f"{name!r} is not a contract topic: give its msg_type")
            msg_type = topic.msg_type
        if topic is not None and msg_type != topic.msg_type:
            raise TypeError(f"{name} carries {topic.msg_type} by contract, not {msg_type}")
        if name in self._conns:
            return self._conns[name]
        if msg_type not in self._store.types:
            raise TypeError(f"{name}: {msg_type} is not a standard ROS 2 Jazzy interface")
        qos = qos or (topic.qos if topic else Qos())
        conn = self._writer.add_connection(name, msg_type, typestore=self._store, serialization_format="cdr",
                                           offered_qos_profiles=[_rosbags_qos(qos)])
        self._conns[name] = conn
        return conn

    # ------------------------------------------------------------------ writing
    def _serialize(self, msg_type: str, msg) -> bytes:
        """Canonical CDR (zero padding, nothing after the last field) of a message of any family."""
        return self._store.serialize_cdr(convert.to_rosbags(msg, self._store), msg_type)

    def write(self, topic: str, stamp_ns: int, msg) -> None:
        """Write one message at stage time ``stamp_ns`` [ns] (its MCAP log time).

        A message with a header (or a Clock) must carry the same stamp. ``msg`` may be
        raw CDR bytes (written as given). ``/experiment/config`` must come first, once.
        """
        if self._closed:
            raise ValueError(f"{self.path}: recorder is closed")
        stamp_ns = int(stamp_ns)
        raw = isinstance(msg, (bytes, bytearray, memoryview))
        if topic not in self._conns:
            self.add_topic(topic, None if raw or topic in TOPICS else convert.message_type_of(msg))
        conn = self._conns[topic]
        if topic == CONFIG.name and sum(self.counts.values()):
            raise ValueError(f"{CONFIG.name} must be written once, first (already written: "
                             f"{dict(self.counts)})")
        if raw:
            data = bytes(msg)
        else:
            msg_type = convert.message_type_of(msg)
            if msg_type != conn.msgtype:
                raise TypeError(f"{topic} carries {conn.msgtype}, got a {msg_type}")
            if hasattr(msg, "header") or hasattr(msg, "clock"):
                got = convert.stamp_ns(msg)
                if got != stamp_ns:
                    raise ValueError(f"{topic}: message stamp {got} ns != log time {stamp_ns} ns "
                                     "(both must be the sample's stage time)")
            data = self._serialize(msg_type, msg)
        self._writer.write(conn, stamp_ns, data)
        self.counts[topic] += 1

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def close(self) -> None:
        """Write the last chunk, the index and summary, and ``metadata.yaml`` (idempotent); an
        ``atomic`` recording is then moved into place."""
        self._finish(None)

    def _finish(self, err) -> None:
        if self._closed:
            return
        self._closed = True
        install, self._install = self._install, None
        try:
            if self._writer is not None and self._writer.storage is not None:
                self._writer.close()
        except BaseException as e:
            err = err or e
            raise
        finally:
            if install is not None:
                install.__exit__(*((type(err), err, err.__traceback__) if err else (None, None, None)))

    def __enter__(self):
        return self

    def __exit__(self, typ, err, tb):
        # after an error: in place, what was written stays readable; atomic, nothing is left
        self._finish(err)
        return False


