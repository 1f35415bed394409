"""``plant_sim`` node: the stage simulator on the ROS graph, in lockstep.

A thin adapter around :func:`stage_sim.plant.plant_step`: for every control sample it
publishes ``/stage/measured``, ``/stage/truth`` and ``/clock``, waits until the
servo command (and, where the stage has them, the dither forces and the SAI mode)
for that sample has arrived, then advances one period.

Safety: the drive saturates at its peak force and thermal (I²t) limit inside the plant
(:func:`stage_sim.plant.plant_step`). The plant stops a trial with a ``fault`` event
(``cause``, ``reason``, ``responsible`` node) and latches the drive at zero force
(inputs arriving later for that trial are not applied; the next trajectory re-arms it)
when

* no input arrives for a sample within ``input_timeout`` (wall clock; for the first sample
  of a trial ``first_input_timeout``: a node may still be starting, e.g. one started late
  loads its compiled kernels before it joins, seconds on a loaded machine): the watchdog,
  naming the silent node -- never a hang;
* an input is NaN or infinite, naming the node that sent it;
* the simulated state diverges (non-finite or runaway) or the table leaves its travel.
"""
from __future__ import annotations

import math
import time

import numpy as np

from experiment_runner.core.batch import Models
from experiment_runner.ros.node import JointStateOut, Lockstep, StageNode, check_preset, finite, warm_up_models
from experiment_runner.ros.nodes import publisher_of
from experiment_runner.ros.run import run_node
from msg_defs import cdr, convert
from msg_defs.topics import SAI_COMMAND
from stage_sim.config import load_preset, preset_from_dict
from stage_sim.plant import DIVERGED, OUT_OF_TRAVEL, STATUS_TEXT, plant_inputs, plant_step

INPUT_TOPIC = {"command": "/stage/command", "dither": "/stage/dither", "sai": SAI_COMMAND.name}
"""Topic of each lockstep input of the plant."""

TABLE, TABLE_BEARING = ("table",), ("table", "bearing")
"""Joint names of ``/stage/measured`` without and with a bearing sensor."""

RESEND_S = 0.25
"""Wall-clock wait for a sample's inputs after which its measurement is published again:
a message sent before its subscriber was matched (start-up) is lost even on a reliable
topic; the controllers answer a repeated sample by repeating their answer."""


class PlantTrial:
    """One trial of the plant, stepped one control period at a time with
    :func:`stage_sim.plant.plant_step` (one-trial arrays, allocated once), from the batch
    engine's initial state (:meth:`experiment_runner.core.batch.Models.initial_state`)."""

    def __init__(self, models: Models, x0: float, seed: int):
        init = models.initial_state([x0])
        self.pm = models.plant
        self.state = init.plant
        self.meas = init.meas
        self.seeds = np.array([seed], np.int64)
        self.status = np.zeros(1, np.int64)
        self.inputs = plant_inputs(1)
        self.k = 0

    def step(self, u: float, d0: float, d1: float, mode: float) -> int:
        """Apply ``u`` [N], dither ``d0, d1`` [N] and SAI ``mode`` over one period; the plant
        status after it (0 ok, else :data:`stage_sim.plant.STATUS_TEXT`)."""
        inp = self.inputs
        inp.u[0], inp.d0[0], inp.d1[0], inp.mode[0] = u, d0, d1, mode
        plant_step(self.pm, self.state, inp, self.k, self.seeds, self.meas, self.status)
        self.k += 1
        return int(self.status[0])



class PlantNode(StageNode):
    """Lockstep plant simulator (one trial at a time, reset at each trajectory)."""

    def __init__(self, **kwargs):
        super().__init__("plant_sim", **kwargs)
        self.timeout = self.param("input_timeout", 5.0, "wall-clock time to wait for a sample's "
                                  "inputs before the trial is aborted [s]", 0.01, 3600.0, attr="timeout")
        self.first_timeout = self.param("first_input_timeout", 30.0, "the same for the first sample of a "
                                        "trial, when a node may still be starting (one started late loads "
                                        "its compiled kernels first) [s]", 0.01, 3600.0, attr="first_timeout")
        self.preset_name = self.param("preset", "", "preset name or YAML path; empty = the preset of "
                                      "/experiment/config", check=check_preset)
        self.pub_measured = JointStateOut(self, "/stage/measured")
        self.pub_truth = JointStateOut(self, "/stage/truth")
        self.pub_clock = self.publisher("/clock")
        self.pub_isolator = JointStateOut(self, "/stage/isolator")
        self.join_runs(self._trajectory)
        self.subscribe("/experiment/events", self._event_in)
        self.subscribe_samples("/stage/command", lambda t, n, p, v, e: self._input(t, "command", e[0]))
        self.subscribe_samples("/stage/dither", lambda t, n, p, v, e: self._input(t, "dither", (e[0], e[1])))
        self.subscribe_samples(SAI_COMMAND, lambda t, n, p, v, e: self._input(t, "sai", p[0]))
        self.preset = load_preset(self.preset_name) if self.preset_name else None
        self.listen_config(self._configure)
        self.sim = None
        self.lock = None
        self._held = None
        self.k = 0
        self.n = 0
        self.waiting_since = None
        self.create_timer(0.1, self._watchdog)
        if self.preset is not None:
            self._build()

    @classmethod
    def warm_up(cls):
        models = warm_up_models()
        PlantTrial(models, 0.0, 0).step(0.0, 0.0, 0.0, models.sai_mode)

    def _configure(self, cfg):
        if not self.preset_name:
            self.preset = preset_from_dict(cfg["preset"], "/experiment/config")
            self._build()

    def _build(self):
        p = self.preset
        self.models = Models.from_preset(p)
        self.pm = self.models.plant
        self.dt_ns = int(round(1e9 / p.controller.rate))
        bodies = ["table"] + [f"body_{i}" for i in range(1, self.pm.n)]
        if self.pm.bear_dof:
            bodies[self.pm.bear_dof] = "bearing"
        self.bodies = tuple(bodies)
        needed = ["command"] + (["dither"] if p.dither else []) + (["sai"] if p.sai_manager else [])
        self.lock = Lockstep(tuple(needed))
        if self._held is not None:
            self._trajectory(self._held)

    def _trajectory(self, msg):
        if self.lock is None:               # config still on its way: start once it is in
            self._held = msg
            return
        self._held = None
        tr = convert.trajectory_from_msg(msg)
        self.trial = tr.trial
        self.start = tr.start
        self.n = len(tr.x_ref)
        self.k = 0
        self.mode = self.models.sai_mode
        self.lock.clear()
        self.ready = {}
        self.sim = PlantTrial(self.models, tr.x_ref[0], self.preset.simulation.seed + tr.trial)
        self._publish_isolator()
        self._publish_sample()

    def _event_in(self, msg):
        """An aborted run: stop the trial, the drive held at zero force (no event of our own)."""
        if self.sim is not None and convert.parse_event(msg.data)["event"] == "abort":
            self.sim = None
            self.waiting_since = None

    def _stamp(self, k):
        return (self.start + k) * self.dt_ns

    def _publish_sample(self):
        stamp = self._stamp(self.k)
        y, yb = self.sim.meas[:, 0].tolist()
        names, pos = (TABLE, (y,)) if math.isnan(yb) else (TABLE_BEARING, (y, yb))
        self.pub_clock.publish(cdr.clock(stamp))
        self.pub_measured.publish(stamp, names, position=pos)
        z = self.sim.state[0][:, 0].tolist()
        n = self.pm.n
        self.pub_truth.publish(stamp, self.bodies, position=z[:n], velocity=z[n:])
        self.waiting_since = time.monotonic()
        self.resends = 0

    def _publish_isolator(self):
        if self.preset.stage.sai is not None:
            self.pub_isolator.publish(self._stamp(self.k), ("isolator",), position=(self.mode,))

    def _input(self, stamp, name, value):
        if self.sim is None or self.lock is None:
            return
        key = stamp // self.dt_ns - self.start
        if key < self.k or key >= self.n:
            return
        if not finite(*(value if isinstance(value, tuple) else (value,))):
            node = publisher_of(INPUT_TOPIC[name])
            self._stop("non_finite_input", f"{name} {value} for sample {key} from {node}", node, key)
            return
        got = self.lock.put(key, name, value)
        if got is not None:
            self.ready[key] = got
            self._advance()

    def _advance(self):
        while self.k < self.n and self.k in self.ready:
            got = self.ready.pop(self.k)
            d0, d1 = got.get("dither", (0.0, 0.0))
            mode = got.get("sai", self.mode)
            status = self.sim.step(got["command"], d0, d1, mode)
            if status:
                cause = {DIVERGED: "diverged", OUT_OF_TRAVEL: "out_of_travel"}[status]
                self._stop(cause, f"{STATUS_TEXT[status]} at t = {self.sim.k * self.pm.dt:.6f} s of trial "
                                  f"{self.trial} (sample {self.k})", self.get_name(), self.k)
                return
            self.k += 1
            if mode != self.mode:
                self.mode = mode
                self._publish_isolator()
            if self.k < self.n:
                self._publish_sample()
            else:
                self.waiting_since = None

    def _watchdog(self):
        if self.sim is None or self.waiting_since is None or self.k >= self.n:
            return
        waited = time.monotonic() - self.waiting_since
        limit = self.first_timeout if self.k == 0 else self.timeout
        if waited <= limit and waited > (self.resends + 1) * RESEND_S:
            self.resends += 1
            self.pub_measured.republish()
        if waited > limit:
            silent = {publisher_of(INPUT_TOPIC[m]) for m in self.lock.missing(self.k)}
            # the SAI manager runs one sample ahead: while the plant waits at sample k it has sent
            # k + 1 already unless it is gone -- then a silent servo may be waiting for its correction
            # (a manager killed between the two deliveries of its last message reached the plant only)
            if "sai" in self.lock.needed and self.k + 1 < self.n and "sai" in self.lock.missing(self.k + 1):
                silent.add(publisher_of(INPUT_TOPIC["sai"]))
            silent = sorted(silent)
            self._stop("watchdog", f"no input for sample {self.k} within {limit:g} s from: "
                                   f"{', '.join(silent)}", silent, self.k, silent=silent)

    def _stop(self, cause, reason, responsible, k, **fields):
        """End the trial at sample ``k``: drive latched at zero force, ``fault`` event."""
        self.sim = None                     # no further input is applied until the next trajectory
        self.lock.clear()
        self.ready = {}
        self.waiting_since = None
        self.fault_event(cause, f"{reason}; drive held at zero force", responsible,
                         stamp_ns=self._stamp(k), trial=self.trial, **fields)


def main(args=None):
    run_node(PlantNode, args)
