"""``recorder`` node: writes every contract topic of the graph to an MCAP recording.

Log time = stage time: the header stamp where the message has one, else the last
stage time heard on ``/clock``. Messages heard before ``/experiment/config`` are held
back so the configuration is written first. Chunks are closed every 0.1 s of stage
time, so a recorder that is killed leaves a file readable up to its last chunk.
"""
from __future__ import annotations

from msg_defs import convert
from msg_defs.node_io import StageNode, run_node
from msg_defs.topics import CONFIG, TOPICS
from experiment_runner.recording import McapRecorder

RECORDED = tuple(name for name in TOPICS if name != CONFIG.name)


class RecorderNode(StageNode):
    def __init__(self, out: str | None = None, **kwargs):
        super().__init__("recorder", **kwargs)
        self.out = self.param("out", out or "run.mcap", "recording path (bag directory or .mcap)",
                              check=lambda v: None if v else "must not be empty")
        self.rec = None
        self.held = []
        self.now_ns = 0
        self.subscribe(CONFIG.name, self._config_in)
        for name in RECORDED:
            self.subscribe(name, lambda m, name=name: self._write(name, m))

    def _config_in(self, msg):
        if self.rec is None:
            self.rec = McapRecorder(self.out, msg.data, overwrite=True)
            for name, stamp, m in self.held:
                self.rec.write(name, stamp, m)
            self.held.clear()

    def _write(self, name, msg):
        if hasattr(msg, "header") or name == "/clock":
            stamp = convert.stamp_ns(msg)
            self.now_ns = max(self.now_ns, stamp)
        elif name == "/experiment/events":
            stamp = convert.parse_event(msg.data)["stamp_ns"]
        else:
            stamp = self.now_ns
        if self.rec is None:
            self.held.append((name, stamp, msg))
        else:
            self.rec.write(name, stamp, msg)

    def close(self):
        if self.rec is not None:
            self.rec.close()


def main(args=None):
    run_node(RecorderNode, args, on_exit=lambda n: n.close())
