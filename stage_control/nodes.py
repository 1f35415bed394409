"""``servo_controller``, ``dither_generator`` and ``sai_manager`` nodes.

Thin adapters around the compiled step functions of :mod:`stage_control.servo`,
:mod:`stage_control.dither` and :mod:`stage_control.sai`, called with one-trial
arrays in the same order as the batch engine, so the graph reproduces the batch
engine's trajectories. Each trial starts from ``/experiment/trajectory`` (state
reset); each sample is computed once its inputs (measurement, SAI command) are in.
"""
from __future__ import annotations

import numpy as np
from msg_defs import convert
from msg_defs.node_io import SAI_COMMAND, Lockstep, StageNode, run_node
from stage_control.dither import build_dither, dither_step, init_dither_state
from stage_control.sai import build_sai, ilc_update, init_sai_state, sai_step
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import SaiManager, preset_from_dict


class _TrialNode(StageNode):
    """Shared trial bookkeeping: config -> models, trajectory -> reset, inputs by sample."""

    inputs: tuple[str, ...] = ("measured",)

    def __init__(self, name, **kwargs):
        super().__init__(name, **kwargs)
        self.preset = None
        self.tr = None
        self.lock = None
        self._held = None
        self._early = []
        self.listen_config(self._configure)
        self.subscribe("/experiment/trajectory", self._trajectory)
        self.subscribe("/stage/measured", lambda m: self._input(m, "measured", m.position[0]))

    def _configure(self, cfg):
        self.preset = preset_from_dict(cfg["preset"], "/experiment/config")
        self.dt_ns = int(round(1e9 / self.preset.controller.rate))
        needed = list(self.inputs)
        if "sai" in needed and self.preset.sai_manager is None:
            needed.remove("sai")
        self.lock = Lockstep(tuple(needed))
        self.build(self.preset)
        if self._held is not None:
            self._trajectory(self._held)

    def _trajectory(self, msg):
        if self.preset is None:             # config still on its way: start once it is in
            self._held = msg
            return
        self._held = None
        self.tr = convert.trajectory_from_msg(msg)
        self.lock.clear()
        self.one = lambda v: np.array([v], float)
        self.reset()
        early, self._early = self._early, []
        for item in early:
            self._put(*item)

    def _input(self, msg, name, value):
        self._put(convert.stamp_ns(msg), name, value)

    def _put(self, stamp, name, value):
        if self.tr is None:                 # an input may overtake its trajectory: keep it
            self._early.append((stamp, name, value))
            return
        k = stamp // self.dt_ns - self.tr.start
        if k >= len(self.tr.x_ref):         # belongs to a trial not started here yet
            self._early.append((stamp, name, value))
        elif k >= 0:
            got = self.lock.put(k, name, value)
            if got is not None:
                self.sample(k, got)

    def stamp(self, k):
        return (self.tr.start + k) * self.dt_ns


class ServoNode(_TrialNode):
    """PID / DOB / feedforward / NIASA servo: /stage/measured -> /stage/command, /stage/reference."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("servo_controller", **kwargs)
        self.pub_command = self.publisher("/stage/command")
        self.pub_reference = self.publisher("/stage/reference")
        self.subscribe(SAI_COMMAND, lambda m: self._input(m, "sai", m.effort[0]))

    def build(self, preset):
        self.model = build_servo(preset.controller, preset.stage)

    def reset(self):
        self.state = init_servo_state(self.model, 1)
        self.u = np.zeros(1)

    def sample(self, k, got):
        xr = self.one(self.tr.x_ref[k] + got.get("sai", 0.0))
        vr = self.one(self.tr.v_ref[k])
        servo_step(self.model, self.state, xr, vr, self.one(got["measured"]), self.u)
        stamp = self.stamp(k)
        self.pub_command.publish(convert.joint_state(None, stamp, ["motor"], effort=[self.u[0]]))
        self.pub_reference.publish(convert.joint_state(None, stamp, ["table"], position=[xr[0]],
                                                       velocity=[vr[0]]))


class DitherNode(_TrialNode):
    """Dither generator with harmonic cancelling: /stage/measured -> /stage/dither."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("dither_generator", **kwargs)
        self.pub = self.publisher("/stage/dither")
        self.subscribe(SAI_COMMAND, lambda m: self._input(m, "sai", m.effort[0]))

    def build(self, preset):
        self.model = build_dither(preset.dither, preset.controller.rate) if preset.dither else None

    def reset(self):
        if self.model is not None:
            self.state = init_dither_state(self.model, 1)
            self.out = np.zeros((2, 1))

    def sample(self, k, got):
        if self.model is None:
            return
        xr = self.one(self.tr.x_ref[k] + got.get("sai", 0.0))
        dither_step(self.model, self.state, k, xr, self.one(self.tr.v_ref[k]),
                    self.one(got["measured"]), self.out)
        self.pub.publish(convert.joint_state(None, self.stamp(k), ["piezo_1", "piezo_2"],
                                             effort=self.out[:, 0]))


class SaiNode(_TrialNode):
    """SAI switch manager: mode and Step II correction one sample ahead; optional ILC
    learning of the correction over trials (Eq. 5.2), published on /stage/correction."""

    def __init__(self, **kwargs):
        super().__init__("sai_manager", **kwargs)
        self.learn = self.param("learn_correction", False, "update the Step II correction after "
                                "every trial with the ILC of Eq. 5.2")
        self.pub = self.publisher(SAI_COMMAND)
        self.pub_correction = self.publisher("/stage/correction")
        self.correction = np.zeros(0)
        self.iteration = 0

    def build(self, preset):
        self.manager = preset.sai_manager
        self.model = build_sai(self.manager or SaiManager(rule="always_compliant"), preset.controller.rate)

    def reset(self):
        self.state = init_sai_state(self.model, 1)
        self.mode, self.xc = np.zeros(1), np.zeros(1)
        self.y = np.full(len(self.tr.x_ref), np.nan)
        self.modes = np.zeros(len(self.tr.x_ref))
        if self.manager is not None:
            self._publish(0)

    def _publish(self, k):
        v = self.tr.v_ref
        ka = min(k + self.model.lead, len(v) - 1)
        sai_step(self.model, self.state, self.correction, k, self.one(v[k]), self.one(v[ka]),
                 self.mode, self.xc)
        self.modes[k] = self.mode[0]
        self.pub.publish(convert.joint_state(None, self.stamp(k), ["isolator"], position=[self.mode[0]],
                                             effort=[self.xc[0]]))

    def sample(self, k, got):
        if self.manager is None:
            return
        self.y[k] = got["measured"]
        if k + 1 < len(self.tr.x_ref):
            self._publish(k + 1)
        elif self.learn and self.manager.ilc is not None:
            self._learn()

    def _learn(self):
        """One ILC iteration from this trial's error after its first compliant->stiff switch."""
        ilc = self.manager.ilc
        n = int(round(ilc.length * self.preset.controller.rate))
        edges = np.flatnonzero((self.modes[:-1] == 1.0) & (self.modes[1:] == 0.0))
        if edges.size == 0:
            return
        k0 = edges[0] + 1
        e = (self.tr.x_ref - self.y)[k0:k0 + n]
        e = np.pad(np.nan_to_num(e), (0, n - e.size))
        u = self.correction if self.correction.size == n else np.zeros(n)
        self.correction = ilc_update(u, e, ilc, self.preset.controller.rate)
        self.iteration += 1
        self.pub_correction.publish(convert.correction_to_msg(
            None, self.correction, iteration=self.iteration, rate=self.preset.controller.rate))


def main_servo(args=None):
    run_node(ServoNode, args)


def main_dither(args=None):
    run_node(DitherNode, args)


def main_sai(args=None):
    run_node(SaiNode, args)
