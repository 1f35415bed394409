"""``sai_manager`` node: the semi-active isolator's switch manager (SAI stages).

One sample ahead of the plant it publishes the isolator mode and the Step II reference
correction (:func:`stage_control.sai.sai_step`) on ``/sai/command``; with
``learn_correction`` it updates the correction after every trial with the ILC of Eq. 5.2
(:func:`stage_control.sai.ilc_update`) and publishes it on ``/stage/correction``. A run
can start from a learned correction: parameter ``initial_correction``. On a stage
without an SAI manager the node runs idle. Shared trial bookkeeping and fault handling:
:mod:`experiment_runner.ros.controller`.
"""
from __future__ import annotations

import numpy as np

from experiment_runner.ros.controller import ControllerNode
from experiment_runner.ros.node import JointStateOut, finite, warm_up_models
from experiment_runner.ros.run import run_node
from msg_defs import convert
from msg_defs.topics import SAI_COMMAND
from stage_control.sai import ilc_update, sai_step

ISOLATOR = ("isolator",)


def _check_correction(values) -> str | None:
    """Parameter validator: None if every value is finite, else which is not."""
    bad = [i for i, v in enumerate(values or ()) if not np.isfinite(v)]
    return f"value {bad[0]} is {values[bad[0]]}: every value must be finite" if bad else None


class SaiNode(ControllerNode):
    """SAI switch manager: mode and Step II correction one sample ahead; optional ILC
    learning of the correction over trials (Eq. 5.2), published on /stage/correction."""

    def __init__(self, **kwargs):
        super().__init__("sai_manager", **kwargs)
        self.learn = self.param("learn_correction", False, "update the Step II correction after "
                                "every trial with the ILC of Eq. 5.2", attr="learn")
        self.correction = np.asarray(self.param(
            "initial_correction", [], "Step II reference correction to start from [m]: one value per "
            "sample after each compliant->stiff switch, e.g. learned by a campaign (empty: none)",
            check=_check_correction), float)
        self.pub = JointStateOut(self, SAI_COMMAND)
        self.pub_correction = self.publisher("/stage/correction")
        self.iteration = 0

    @classmethod
    def warm_up(cls):
        models = warm_up_models()
        sai_step(models.sai, models.initial_state([0.0]).sai, np.zeros(0), 0, *(np.zeros(1) for _ in range(4)))

    def active(self, preset):
        return preset.sai_manager is not None

    def build(self, preset):
        self.manager = preset.sai_manager
        self.model = self.models.sai

    def reset(self):
        self.state = self.models.initial_state([self.tr.x_ref[0]]).sai
        self.mode, self.xc = np.zeros(1), np.zeros(1)
        self.v, self.va = np.zeros(1), np.zeros(1)          # one-trial inputs
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
        self.v[0], self.va[0] = v[k], v[ka]
        sai_step(self.model, self.state, self.correction, k, self.v, self.va, self.mode, self.xc)
        self.modes[k] = mode = self.mode[0]
        self.sent.pop(k - 2, None)
        self.sent[k] = (mode, self.xc[0])
        self.pub.publish(self.stamp(k), ISOLATOR, position=(mode,), effort=(self.xc[0],))

    def resend(self, k):
        """Sample ``k``'s command (sent one sample ahead) and ``k + 1``'s, as sent."""
        for j in (k, k + 1):
            if j in self.sent:
                self.pub.publish(self.stamp(j), ISOLATOR, position=(self.sent[j][0],),
                                 effort=(self.sent[j][1],))

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


def main(args=None):
    run_node(SaiNode, args)
