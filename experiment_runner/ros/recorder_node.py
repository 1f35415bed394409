"""``recorder`` node: writes every contract topic of the graph to an MCAP recording.

Log time = stage time: the header stamp where the message has one, else the last
stage time heard on ``/clock``. Messages heard before ``/experiment/config`` are held
back so the configuration is written first. Chunks are closed every 0.1 s of stage
time, so a recorder that is killed leaves a file readable up to its last chunk.

On SIGINT / SIGTERM the recorder first takes the messages still on their way (it may be
behind the loop) until none has come for ``DRAIN_IDLE_S`` (at most ``DRAIN_MAX_S``). It
counts the per-sample messages that never reached it (a gap in a topic's sample stamps:
lost on the way, or the recorder fell more than the topics' 0.1 s history behind, e.g.
stopped) and, if any, writes a ``fault`` event (cause ``recording_incomplete``) saying how
many of which topic before it closes the file; ``nanostage graph`` then exits 3.

A recorder stopped (SIGINT / SIGTERM) while the run is still open (configuration heard, no
``run_end``: the sequencer is gone) writes an ``abort`` and a ``run_end`` event itself,
naming the sequencer, before it closes the file. An existing recording is never
replaced unless ``overwrite`` is set: a recorder restarted mid-run writes the next free
``<out>_<i>`` bag, and the part its predecessor wrote stays as it was.
"""
from __future__ import annotations

import time
from pathlib import Path

import yaml

from experiment_runner.core.recording import McapRecorder, bag_layout
from experiment_runner.ros.node import StageNode
from experiment_runner.ros.run import run_node
from msg_defs import cdr, convert
from msg_defs.topics import (CLOCK, COMMAND, CONFIG, CONTRACT_TOPICS, DITHER, MEASURED, REFERENCE, TOPICS, TRAJECTORY,
                             TRUTH)

RECORDED = tuple(name for name in TOPICS if name != CONFIG.name)
RAW = (REFERENCE.name, COMMAND.name, MEASURED.name, TRUTH.name, DITHER.name, CLOCK.name)
"""Per-sample topics taken as CDR bytes and written as they come once they are canonical
(:mod:`msg_defs.cdr`: what the graph's nodes publish; another publisher's bytes are
re-encoded), with no message object. The recorder asks for the samples published before
discovery matched it with their publisher (up to 0.1 s of them), and makes its
``/experiment/trajectory`` subscription, which the sequencer waits for, last."""


DRAIN_IDLE_S = 0.3
"""On stop: the recorder closes once no message has come for this long [s]."""

READY_TIMEOUT_S = 5.0
"""The recorder joins runs once it has matched every publisher the graph knows of each recorded
topic (at least one of each contract topic), or after this long [s] (a node started
deliberately late must not hold the run)."""


class RecorderNode(StageNode):
    def __init__(self, out: str | None = None, overwrite: bool = False, **kwargs):
        super().__init__("recorder", **kwargs)
        self.out = self.param("out", out or "run.mcap", "recording path (bag directory or .mcap)",
                              check=lambda v: None if v else "must not be empty")
        self.overwrite = self.param("overwrite", overwrite, "replace an existing recording at `out` "
                                    "(false: write the next free <out>_<i> instead)")
        self.rec = None
        self.open_run = False               # config heard, no run_end yet
        self.trial = None                   # trial of the last trial_start heard
        self.held = []
        self.now_ns = 0
        self.last_ns = {}                   # per-sample topic -> stamp written last
        self.lost = {}                      # per-sample topic -> samples that never came (gaps)
        self.early_steps = {}               # per-sample topic -> stamp steps seen before the config
        self.dt_ns = None                   # control period of the run (from its config)
        self.end_ns = None                  # last sample of the last trial that ended
        self.last_heard = time.monotonic()
        self.subscribe(CONFIG.name, self._config_in)
        subs = {}
        for name in RECORDED:
            if name in RAW:
                canonical = (cdr.JointStateReader().canonical if TOPICS[name].msg_type == cdr.JOINT_STATE
                             else lambda data: cdr.canonical(data, cdr.CLOCK))
                subs[name] = self.subscribe(name, lambda data, name=name, c=canonical: self._write_raw(name, data, c),
                                            record=True, raw=True)
            elif name != TRAJECTORY.name:
                subs[name] = self.subscribe(name, lambda m, name=name: self._write(name, m), record=True)
        # ready for a run once every recorded topic's publishers that the graph knows are matched,
        # and at least one of each contract topic (a run that starts before the recorder hears a
        # node loses that node's first samples beyond the topic's history, or all of them if the
        # node stops early: CI lost the dither's, an optional topic), at most READY_TIMEOUT_S
        def ready():
            return all(s.get_publisher_count() >= max(int(t in CONTRACT_TOPICS), self.count_publishers(t))
                       for t, s in subs.items())
        self.join_runs(lambda m: self._write(TRAJECTORY.name, m), ready=ready, ready_timeout=READY_TIMEOUT_S)

    def _write_raw(self, topic: str, data: bytes, canonical):
        """A per-sample message (JointState or Clock, CDR bytes), written in its canonical CDR;
        a sample sent again (the lockstep's retry) is written once."""
        stamp = cdr.stamp_ns(data)
        last = self.last_ns.get(topic, -1)
        if stamp <= last:
            return
        # a gap in the stamps: samples that never came (after run_end nothing belongs to the run);
        # before the config (and with it the control period) is heard -- it may arrive after the
        # first samples on a loaded machine -- the steps are kept and counted when it comes
        if last >= 0:
            if self.dt_ns is None:
                self.early_steps.setdefault(topic, []).append(stamp - last)
            elif self.open_run:
                self._count_gap(topic, stamp - last)
        self.last_ns[topic] = stamp
        self.now_ns = max(self.now_ns, stamp)
        self._write(topic, canonical(data), stamp)

    def _count_gap(self, topic: str, step_ns: int):
        if step_ns > self.dt_ns:
            self.lost[topic] = self.lost.get(topic, 0) + step_ns // self.dt_ns - 1

    def _config_in(self, msg):
        self.last_heard = time.monotonic()
        rate = ((yaml.safe_load(msg.data) or {}).get("preset") or {}).get("controller", {}).get("rate")
        if rate and self.dt_ns is None:
            self.dt_ns = int(round(1e9 / float(rate)))
            for topic, steps in self.early_steps.items():
                for step in steps:
                    self._count_gap(topic, step)
            self.early_steps.clear()
        if self.rec is None:
            self.open_run = True
            self.rec = McapRecorder(self._free_path(), msg.data, overwrite=self.overwrite)
            for name, stamp, m in self.held:
                self.rec.write(name, stamp, m)
            self.held.clear()

    def _free_path(self) -> Path:
        """``out``, or (an existing recording, no ``overwrite``) the first free ``<out>_<i>``."""
        bag, _ = bag_layout(self.out)
        if self.overwrite or not bag.exists():
            return bag
        i = 2
        while bag.with_name(f"{bag.name}_{i}").exists():
            i += 1
        free = bag.with_name(f"{bag.name}_{i}")
        self.get_logger().warning(f"{bag} exists (a recorder before me?): recording to {free}")
        return free

    def _write(self, name, msg, stamp=None):
        self.last_heard = time.monotonic()
        if stamp is not None:
            pass
        elif hasattr(msg, "header") or name == "/clock":
            stamp = convert.stamp_ns(msg)
            self.now_ns = max(self.now_ns, stamp)
        elif name == "/experiment/events":
            ev = convert.parse_event(msg.data)
            stamp = ev["stamp_ns"]
            if ev["event"] == "run_end":
                self.open_run = False
            elif ev["event"] == "trial_start":
                self.trial = ev["trial"]
            elif ev["event"] == "trial_end":
                self.end_ns = max(stamp, self.end_ns or 0)
        else:
            stamp = self.now_ns
        if self.rec is None:
            self.held.append((name, stamp, msg))
        else:
            self.rec.write(name, stamp, msg)

    def draining(self) -> bool:
        """Whether messages are still coming (on stop: keep taking them)."""
        return time.monotonic() - self.last_heard < DRAIN_IDLE_S

    def close(self):
        """Close the recording; lost samples are reported and a run still open is marked
        aborted in it first."""
        if self.rec is None:
            return
        if self.dt_ns and self.end_ns is not None:    # up to the last trial_end, every sample was sent
            for topic, last in self.last_ns.items():
                if self.end_ns > last:
                    self.lost[topic] = self.lost.get(topic, 0) + (self.end_ns - last) // self.dt_ns
        if self.lost:
            lost = ", ".join(f"{n} sample(s) of {t}" for t, n in sorted(self.lost.items()))
            reason = (f"recording_incomplete: {lost} never reached the recorder (lost on the way, or the "
                      "recorder fell more than the topics' 0.1 s history behind: stopped or overloaded)")
            self.get_logger().error(reason)
            self.rec.write("/experiment/events", self.now_ns, convert.event_msg(
                None, "fault", stamp_ns=self.now_ns, reason=reason, cause="recording_incomplete",
                responsible=[self.get_name()], lost=dict(self.lost), node=self.get_name()))
        if self.open_run:
            reason = ("recording stopped before run_end was heard: experiment_sequencer stopped or "
                      "was killed (or this recorder started after the run ended)")
            self.get_logger().error(reason)
            for kind, extra in (("abort", {"trial": self.trial, "responsible": "experiment_sequencer"}),
                                ("run_end", {})):
                self.rec.write("/experiment/events", self.now_ns, convert.event_msg(
                    None, kind, stamp_ns=self.now_ns, reason=reason if kind == "abort" else "aborted",
                    node=self.get_name(), **extra))
            self.open_run = False
        self.rec.close()


def main(args=None):
    run_node(RecorderNode, args, on_exit=lambda n: n.close(), drain=lambda n: n.draining())
