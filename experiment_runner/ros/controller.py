"""What the three controller nodes share (``servo_controller``, ``dither_generator``,
``sai_manager``: one module each), around the compiled step functions of
:mod:`stage_control.servo`, :mod:`stage_control.dither` and :mod:`stage_control.sai`.

Each is called with one-trial arrays in the same order as the batch engine, from the
same models and initial state (:meth:`experiment_runner.core.batch.Models.from_preset`,
:meth:`~experiment_runner.core.batch.Models.initial_state`), so the graph reproduces the
batch engine's trajectories bit for bit. Each trial starts from
``/experiment/trajectory`` (state reset); each sample is computed once its inputs
(measurement, SAI command) are in.

Safety: a node stops computing a trial and publishes a ``fault`` event (see
:meth:`experiment_runner.ros.node.StageNode.fault_event`) when an input is NaN or infinite
(naming the node that sent it), when its own state or output stops being finite (naming
itself), when it would join a trial after the trial's first sample (its state would start
from rest in mid-motion: a node restarted mid-run), and -- the servo -- when a reference
lies outside the stage's travel (refused before the trial starts).
"""
from __future__ import annotations


from experiment_runner.core.batch import Models
from experiment_runner.ros.node import Lockstep, StageNode, check_preset, finite
from experiment_runner.ros.nodes import publisher_of
from msg_defs import convert
from msg_defs.topics import SAI_COMMAND
from stage_sim.config import load_preset, preset_from_dict


_FIELD = {"position": 1, "velocity": 2, "effort": 3}
"""Index of a JointState array in ``(names, position, velocity, effort)``."""


class ControllerNode(StageNode):
    """Shared trial bookkeeping: config -> models, trajectory -> reset, inputs by sample."""

    inputs: tuple[str, ...] = ("measured",)

    def __init__(self, name, **kwargs):
        super().__init__(name, **kwargs)
        self._inputs, self._input_specs = [], []     # per-sample subscriptions
        self._sender = {"sai": publisher_of(SAI_COMMAND.name)}   # input name -> node that publishes it
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
        """Per-sample input ``name`` = ``<field>[0]`` of the JointState on ``topic`` (not subscribed
        while this node is unused)."""
        self._sender[name] = publisher_of(getattr(topic, "name", topic))
        self._input_specs.append((topic, name, field))
        if self.preset is None or self.active(self.preset):
            self._inputs.append(self._subscribe_input(topic, name, field))

    def _subscribe_input(self, topic, name, field):
        i = _FIELD[field]
        return self.subscribe_samples(topic, lambda stamp, *fields: self._put(stamp, name, fields[i][0]))

    def _listen_inputs(self, on: bool):
        if on and not self._inputs:
            self._inputs = [self._subscribe_input(t, n, f) for t, n, f in self._input_specs]
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
        self.models = Models.from_preset(self.preset)
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

    def build(self, preset):
        """Set up for ``preset`` (``self.models`` is built)."""

    def reset(self):
        """Start trial ``self.tr`` from rest."""

    def sample(self, k, got):
        """Compute sample ``k`` from its inputs ``got`` (``{input name: value}``) and publish."""

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
