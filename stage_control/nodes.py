"""``servo_controller``, ``dither_generator`` and ``sai_manager`` nodes.

Thin adapters around the compiled step functions of :mod:`stage_control.servo`,
:mod:`stage_control.dither` and :mod:`stage_control.sai`, called with one-trial
arrays in the same order as the batch engine, so the graph reproduces the batch
engine's trajectories. Each trial starts from ``/experiment/trajectory`` (state
reset); each sample is computed once its inputs (measurement, SAI command) are in.

Safety: a node stops computing a trial and publishes a ``fault`` event (see
:meth:`msg_defs.node_io.StageNode.fault_event`) when an input is NaN or infinite (naming
the node that sent it), when its own state or output stops being finite (naming itself),
when it would join a trial after the trial's first sample (its state would start from
rest in mid-motion: a node restarted mid-run), and -- the servo -- when a reference lies
outside the stage's travel (refused before the trial starts). The servo's command is
saturated at the drive's peak force (:func:`stage_control.servo.build_servo`).
"""
from __future__ import annotations

import numpy as np
from msg_defs import convert
from msg_defs.node_io import NODE_OF_INPUT, SAI_COMMAND, JointStateOut, Lockstep, StageNode, finite, run_node
from stage_control.dither import build_dither, dither_step, init_dither_state
from stage_control.sai import build_sai, ilc_update, init_sai_state, sai_step
from stage_control.servo import build_servo, check_reference, init_servo_state, servo_step
from stage_sim.config import SaiManager, load_preset, preset_from_dict
from stage_sim.node import check_preset


class _TrialNode(StageNode):
    """Shared trial bookkeeping: config -> models, trajectory -> reset, inputs by sample."""

    inputs: tuple[str, ...] = ("measured",)

    def __init__(self, name, **kwargs):
        super().__init__(name, **kwargs)
        self._inputs, self._input_specs = [], []     # per-sample subscriptions
        self._sender = {"sai": "sai_manager"}        # input name -> node that publishes it
        self.stopped = False                         # this trial stopped on a fault
        self.preset_name = self.param("preset", "", "preset name or YAML path; empty = the preset of "
                                      "/experiment/config", check=check_preset)
        self.preset = None
        self.tr = None
        self.lock = None
        self._held = None
        self._early = []
        self.listen_config(self._configure)
        if self.preset_name:
            self._configure(None)
        self.join_runs(self._trajectory)
        self.subscribe_input("/stage/measured", "measured", "position")

    def active(self, preset) -> bool:
        """Whether the preset uses this node (an unused one drops its per-sample subscriptions)."""
        return True

    def subscribe_input(self, topic, name, field):
        """Per-sample input ``name`` = ``msg.<field>[0]`` (not subscribed while this node is unused)."""
        self._sender[name] = NODE_OF_INPUT.get(getattr(topic, "name", topic), "?")
        self._input_specs.append((topic, name, field))
        if self.preset is None or self.active(self.preset):
            self._inputs.append(self.subscribe(topic, lambda m: self._input(m, name, getattr(m, field)[0])))

    def _listen_inputs(self, on: bool):
        if on and not self._inputs:
            self._inputs = [self.subscribe(t, lambda m, n=n, f=f: self._input(m, n, getattr(m, f)[0]))
                            for t, n, f in self._input_specs]
        elif not on:
            for sub in self._inputs:
                self.destroy_subscription(sub)
            self._inputs = []

    def _configure(self, cfg):
        if self.preset is not None and cfg is not None and self.preset_name:
            return                          # the preset parameter wins over the run's config
        self.preset = (load_preset(self.preset_name) if self.preset_name
                       else preset_from_dict(cfg["preset"], "/experiment/config"))
        self.dt_ns = int(round(1e9 / self.preset.controller.rate))
        needed = list(self.inputs)
        if "sai" in needed and self.preset.sai_manager is None:
            needed.remove("sai")
        self.lock = Lockstep(tuple(needed))
        self._listen_inputs(self.active(self.preset))   # e.g. no dither on this stage: hear no samples
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
        self.last_k = -1                    # last sample computed
        self.stopped = False
        problem = self.refuse(self.tr)
        if problem:
            self._stop(*problem, 0)
            return
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
        elif self.stopped:
            return
        elif k <= self.last_k:              # computed already: the plant sent this sample again
            if k == self.last_k >= 0 and name == "measured":
                self.resend(k)              # (our answer may have been lost): answer again
        elif k >= 0:
            if not finite(value):
                self._stop("non_finite_input", f"{name} {value} for sample {k} from {self._sender[name]}",
                           self._sender[name], k)
                return
            got = self.lock.put(k, name, value)
            if got is not None:
                if self.last_k < 0 and k > 0:
                    self._stop("joined_mid_trial", f"{self.get_name()} got its first inputs of trial "
                               f"{self.tr.trial} at sample {k}, not 0 (restarted mid-run?): its state "
                               "would start from rest in mid-motion", self.get_name(), k)
                    return
                self.last_k = k
                self.sample(k, got)
                if not self.healthy():
                    self._stop("diverged", f"{self.get_name()} state or output not finite at sample {k}",
                               self.get_name(), k)

    def _stop(self, cause, reason, responsible, k):
        """Stop computing this trial (until the next trajectory) and publish a ``fault`` event."""
        self.stopped = True
        self.lock.clear()
        self.fault_event(cause, reason, responsible, stamp_ns=self.stamp(k), trial=self.tr.trial)

    def refuse(self, tr) -> tuple[str, str, str] | None:
        """``(cause, reason, responsible)`` if this node refuses trial ``tr``, else None."""
        return None

    def healthy(self) -> bool:
        """Whether the state and the last output are finite (checked after every sample)."""
        return True

    def resend(self, k):
        """Publish again what was published for sample ``k`` (nothing is recomputed)."""

    def stamp(self, k):
        return (self.tr.start + k) * self.dt_ns


class ServoNode(_TrialNode):
    """PID / DOB / feedforward / NIASA servo: /stage/measured -> /stage/command, /stage/reference."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("servo_controller", **kwargs)
        self.pub_command = JointStateOut(self, "/stage/command")
        self.pub_reference = JointStateOut(self, "/stage/reference")
        self.subscribe(SAI_COMMAND, lambda m: self._input(m, "sai", m.effort[0]))

    def build(self, preset):
        self.model = build_servo(preset.controller, preset.stage)

    def reset(self):
        self.state = init_servo_state(self.model, 1)
        self.u = np.zeros(1)

    def refuse(self, tr):
        problem = check_reference(tr.x_ref, self.preset.stage.travel)
        return problem and ("reference_out_of_travel", f"trial {tr.trial} refused: {problem}",
                            "experiment_sequencer")

    def healthy(self):
        return finite(self.u, self.state)

    def sample(self, k, got):
        xr = self.one(self.tr.x_ref[k] + got.get("sai", 0.0))
        vr = self.one(self.tr.v_ref[k])
        servo_step(self.model, self.state, xr, vr, self.one(got["measured"]), self.u)
        stamp = self.stamp(k)
        self.pub_command.publish(stamp, ["motor"], effort=self.u)
        self.pub_reference.publish(stamp, ["table"], position=xr, velocity=vr)

    def resend(self, k):
        self.pub_command.republish()
        self.pub_reference.republish()


class DitherNode(_TrialNode):
    """Dither generator with harmonic cancelling: /stage/measured -> /stage/dither."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("dither_generator", **kwargs)
        self.pub = JointStateOut(self, "/stage/dither")
        self.subscribe_input(SAI_COMMAND, "sai", "effort")

    def active(self, preset):
        return preset.dither is not None

    def build(self, preset):
        self.model = build_dither(preset.dither, preset.controller.rate) if preset.dither else None

    def reset(self):
        if self.model is not None:
            self.state = init_dither_state(self.model, 1)
            self.out = np.zeros((2, 1))

    def healthy(self):
        return self.model is None or finite(self.out, self.state)

    def sample(self, k, got):
        if self.model is None:
            return
        xr = self.one(self.tr.x_ref[k] + got.get("sai", 0.0))
        dither_step(self.model, self.state, k, xr, self.one(self.tr.v_ref[k]),
                    self.one(got["measured"]), self.out)
        self.pub.publish(self.stamp(k), ["piezo_1", "piezo_2"], effort=self.out[:, 0])

    def resend(self, k):
        if self.model is not None:
            self.pub.republish()


class SaiNode(_TrialNode):
    """SAI switch manager: mode and Step II correction one sample ahead; optional ILC
    learning of the correction over trials (Eq. 5.2), published on /stage/correction."""

    def __init__(self, **kwargs):
        super().__init__("sai_manager", **kwargs)
        self.learn = self.param("learn_correction", False, "update the Step II correction after "
                                "every trial with the ILC of Eq. 5.2", attr="learn")
        self.pub = JointStateOut(self, SAI_COMMAND)
        self.pub_correction = self.publisher("/stage/correction")
        self.correction = np.zeros(0)
        self.iteration = 0

    def active(self, preset):
        return preset.sai_manager is not None

    def build(self, preset):
        self.manager = preset.sai_manager
        self.model = build_sai(self.manager or SaiManager(rule="always_compliant"), preset.controller.rate)

    def reset(self):
        self.state = init_sai_state(self.model, 1)
        self.mode, self.xc = np.zeros(1), np.zeros(1)
        self.y = np.full(len(self.tr.x_ref), np.nan)
        self.modes = np.zeros(len(self.tr.x_ref))
        self.sent = {}
        if self.manager is not None:
            self._publish(0)

    def healthy(self):
        return finite(self.mode, self.xc)

    def _publish(self, k):
        v = self.tr.v_ref
        ka = min(k + self.model.lead, len(v) - 1)
        sai_step(self.model, self.state, self.correction, k, self.one(v[k]), self.one(v[ka]),
                 self.mode, self.xc)
        self.modes[k] = self.mode[0]
        self.sent = {j: v for j, v in self.sent.items() if j >= k - 1}
        self.sent[k] = (self.mode[0], self.xc[0])
        self.pub.publish(self.stamp(k), ["isolator"], position=self.mode, effort=self.xc)

    def resend(self, k):
        """Sample ``k``'s command (sent one sample ahead) and ``k + 1``'s, as sent."""
        for j in (k, k + 1):
            if j in self.sent:
                self.pub.publish(self.stamp(j), ["isolator"], position=[self.sent[j][0]],
                                 effort=[self.sent[j][1]])

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
