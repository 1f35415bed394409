"""``experiment_sequencer`` node: runs an experiment file through the graph.

It publishes the run configuration, then each trial's trajectory (the same
:func:`experiment_runner.core.experiment.build_trials` the batch engine uses), cuts the
run into trials with ``/experiment/events``, computes each trial's metrics from
what it hears on the contract topics and publishes them on ``/experiment/results``.
If samples stop coming (a node died or hangs), the plant goes back to an earlier
sample (it restarted), the nodes are not all there within ``start_timeout``, another
sequencer is on the domain, or a node reports a ``fault``, the trial is marked aborted
with the reason and the node responsible (``abort`` event), the run ends (``run_end``)
and the executable exits 1.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np
import yaml

from experiment_runner.core.experiment import build_trials, experiment_preset, load_experiment, trial_metrics
from experiment_runner.ros.node import StageNode
from experiment_runner.ros.nodes import JOINING, publisher_of
from experiment_runner.ros.run import run_node
from msg_defs import convert
from msg_defs.topics import TRAJECTORY
from stage_sim.config import ConfigError


def _check_experiment(name):
    try:
        load_experiment(name)
    except ConfigError as err:
        return str(err)
    return None


class SequencerNode(StageNode):
    """Publishes trials one after the other and judges each one."""

    def __init__(self, experiment: str | None = None, **kwargs):
        super().__init__("experiment_sequencer", **kwargs)
        name = self.param("experiment", experiment or "fi_p2p_5um",
                          "experiment name (shipped) or YAML path", check=_check_experiment)
        self.timeout = self.param("sample_timeout", 5.0, "wall-clock time without a new sample "
                                  "before the trial is aborted [s]", 0.01, 3600.0, attr="timeout")
        self.wait_nodes = self.param("wait_for_nodes", len(JOINING), "subscribers of /experiment/trajectory "
                                     f"to wait for before starting ({len(JOINING)}: {', '.join(JOINING)}; "
                                     "fewer, and the recorder may miss the first events)", 0, 100,
                                     attr="wait_nodes")
        self.start_delay = self.param("start_delay", 1.0, "wall-clock time to wait once the nodes are "
                                      "there, so they discover each other too (what a publisher "
                                      "sends before its subscriber matched is lost) [s]", 0.0, 60.0,
                                      attr="start_delay")
        self.start_timeout = self.param("start_timeout", 60.0, "wall-clock time to wait for the nodes "
                                        "before the run is aborted naming the missing ones [s]",
                                        0.1, 3600.0, attr="start_timeout")
        self.ready_since = None
        self.exp = load_experiment(name)
        self.preset = experiment_preset(self.exp)
        self.trials = build_trials(self.exp, self.preset)
        self.rate = self.preset.controller.rate
        self.dt_ns = int(round(1e9 / self.rate))
        self.pub_config = self.publisher("/experiment/config")
        self.pub_traj = self.publisher("/experiment/trajectory")
        self.pub_results = self.publisher("/experiment/results")
        # every sample counts for the metrics: also those sent before discovery matched us (record)
        self.subscribe_samples("/stage/measured", lambda t, n, p, v, e: self._sample(t, "measured", p[0]),
                               record=True)
        self.subscribe_samples("/stage/reference", lambda t, n, p, v, e: self._sample(t, "reference", p[0]),
                               record=True)
        self.subscribe("/experiment/events", self._event_in)
        self.results: list[dict] = []
        self.done = False
        self.aborted = None
        self.current = -1
        self.start = 0
        self.k_meas = self.k_ref = -1
        self.last_progress = self.t_created = time.monotonic()
        self.create_timer(0.05, self._tick)

    def config_yaml(self) -> str:
        return yaml.safe_dump({"experiment": self.exp.model_dump(), "preset": self.preset.model_dump()},
                              sort_keys=False)

    # ----------------------------------------------------------------- run control
    def _tick(self):
        if self.done:
            return
        if self.current < 0:
            self._wait_for_nodes()
            return
        if time.monotonic() - self.last_progress > self.timeout:
            n = len(self.y)
            if self.k_meas == n - 1 and self.k_ref == n - 1:
                # the loop reached the end, but records were lost on the way (not resent: no node waits for them)
                stale = "reference" if np.isnan(self.xr).any() else "measured"
                lost = int(np.isnan(self.xr if stale == "reference" else self.y).sum())
                node = publisher_of(f"/stage/{stale}")
                self._abort(f"{lost} {stale} sample(s) of the trial never arrived (lost); its metrics "
                            "cannot be computed", node)
                return
            # a live plant sends its waiting sample again every 0.25 s: no measured message at all
            # (not even a repeat) means the plant is gone or stopped, whatever the servo last sent
            # (a plant killed mid-publish may have reached us but not the servo)
            quiet = time.monotonic() - self.last_measured > self.timeout
            stale = "measured" if quiet or self.k_meas <= self.k_ref else "reference"
            node = publisher_of(f"/stage/{stale}")
            self._abort(f"no {stale} sample after sample {max(self.k_meas, self.k_ref)} within "
                        f"{self.timeout} s", node)

    def _wait_for_nodes(self):
        """Start once ``wait_nodes`` subscribers are matched (and ``start_delay`` passed);
        abort if another sequencer publishes trajectories on this domain, or if the nodes
        are not all there within ``start_timeout``."""
        now = time.monotonic()
        if self.count_publishers("/experiment/trajectory") > 1:
            self._abort("another experiment_sequencer publishes /experiment/trajectory on ROS domain "
                        f"{self.context.get_domain_id()}: its latched trajectories would mix into this run",
                        "experiment_sequencer")
            return
        if self.pub_traj.get_subscription_count() < self.wait_nodes:
            self.ready_since = None
            if now - self.t_created > self.start_timeout:
                joined = {i.node_name for i in self.get_subscriptions_info_by_topic(TRAJECTORY.name)}
                present = set(self.get_node_names())
                waiting = [n for n in JOINING if n not in joined]
                missing = [n for n in waiting if n not in present]
                starting = [n for n in waiting if n in present]       # made, not joined: loading its kernels
                which = "; ".join(f"{label}: {', '.join(nodes)}" for label, nodes in
                                  (("missing", missing), ("still starting", starting)) if nodes)
                self._abort(f"only {self.pub_traj.get_subscription_count()} of {self.wait_nodes} nodes "
                            f"after {self.start_timeout} s; {which or 'missing: ?'}", waiting)
            return
        if self.ready_since is None:
            self.ready_since = now
        if now - self.ready_since >= self.start_delay:
            self.pub_config.publish(convert.string_msg(None, self.config_yaml()))
            self.event("run_start", stamp_ns=0, case=self.exp.name, window_m=self.exp.window)
            self._next_trial()

    def _next_trial(self):
        self.current += 1
        if self.current >= len(self.trials):
            last = self.start + len(self.trials[-1].x_ref) - 1 if self.trials else 0
            self.event("run_end", stamp_ns=last * self.dt_ns, case=self.exp.name)   # = last trial_end
            self.done = True
            return
        tr = self.trials[self.current]
        if self.current:
            self.start += len(self.trials[self.current - 1].x_ref)
        n = len(tr.x_ref)
        self.y = np.full(n, np.nan)
        self.xr = np.full(n, np.nan)
        self.unheard = {"measured": n, "reference": n}     # samples of each still nan
        self.k_meas = self.k_ref = -1
        settle = [s for s in tr.segments if s.kind == "settle"]
        extra = {}
        if settle:
            extra = {"target_m": float(tr.x_ref[settle[0].stop - 1]),
                     "settle_start_ns": (self.start + settle[0].start) * self.dt_ns}
        self.event("trial_start", stamp_ns=self.start * self.dt_ns, trial=tr.index, case=tr.case,
                   step_index=0 if settle else None, window_m=tr.window, **extra)
        self.last_progress = self.last_measured = time.monotonic()
        self.pub_traj.publish(convert.trajectory_to_msg(None, tr.x_ref, tr.v_ref, trial=tr.index,
                                                        case=tr.case, start=self.start, rate=self.rate))

    def _sample(self, stamp, name, value):
        if self.done or self.current < 0:
            return
        k = stamp // self.dt_ns - self.start
        n = len(self.y)
        if not 0 <= k < n:
            return
        now = time.monotonic()
        if name == "measured":
            self.last_measured = now
            if k < self.k_meas:             # not a resend (that is k_meas): a plant started afresh
                self._abort(f"plant_sim published sample {k} of trial {self.trials[self.current].index} "
                            f"after sample {self.k_meas}: it restarted mid-run", "plant_sim")
                return
            values = self.y
            self.k_meas = max(self.k_meas, k)
        else:
            values = self.xr
            self.k_ref = max(self.k_ref, k)
        self.unheard[name] += math.isnan(value) - math.isnan(values[k])
        values[k] = value
        self.last_progress = now
        if self.k_meas == n - 1 and self.k_ref == n - 1 and not self.unheard["measured"] \
                and not self.unheard["reference"]:
            self._finish_trial()

    def _finish_trial(self):
        tr = self.trials[self.current]
        res = trial_metrics(tr, self.y, self.xr, self.rate)
        res["node"] = self.get_name()
        self.results.append(res)
        self.pub_results.publish(convert.string_msg(None, convert.to_json(res)))
        self.event("trial_end", stamp_ns=(self.start + len(self.y) - 1) * self.dt_ns, trial=tr.index,
                   case=tr.case, window_m=tr.window)
        self._next_trial()

    def _event_in(self, msg):
        ev = convert.parse_event(msg.data)
        if ev["event"] == "fault" and not self.done:
            self._abort(ev.get("reason") or "fault", ev.get("responsible") or ev.get("silent") or ev.get("node"))

    def _abort(self, reason, node):
        nodes = node if isinstance(node, str) else ", ".join(node or [])
        tr = self.trials[self.current] if 0 <= self.current < len(self.trials) else None
        self.aborted = {"trial": None if tr is None else tr.index, "reason": reason, "node": nodes}
        heard = max(getattr(self, "k_meas", -1), getattr(self, "k_ref", -1), 0)
        stamp = (self.start + heard) * self.dt_ns        # the last sample heard, so it sorts after it
        self.event("abort", stamp_ns=stamp, trial=None if tr is None else tr.index,
                   case=self.exp.name, reason=f"{reason} (node: {nodes})", responsible=nodes)
        self.event("run_end", stamp_ns=stamp, case=self.exp.name, reason="aborted")
        self.done = True


def main(args=None):
    def on_exit(node):
        time.sleep(0.5)                     # let the last events reach the recorder
        if node.aborted:
            a = node.aborted
            print(f"run aborted (trial {a['trial']}): {a['reason']} (node: {a['node']})", file=sys.stderr)
            return 1                        # an aborted run is a failed run (as in one process)
        return 0

    run_node(SequencerNode, args, until=lambda n: n.done, on_exit=on_exit)
