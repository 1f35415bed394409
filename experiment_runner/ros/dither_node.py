"""``dither_generator`` node: dither forces with harmonic cancelling (VAN stages).

Lockstep: for each control sample, once ``/stage/measured`` (and the SAI manager's
correction on SAI stages) is in, one call of :func:`stage_control.dither.dither_step`
gives the two piezo forces, published on ``/stage/dither``. On a stage without dither
the node runs idle (no per-sample subscriptions). Shared trial bookkeeping and fault
handling: :mod:`experiment_runner.ros.controller`.
"""
from __future__ import annotations

import numpy as np

from experiment_runner.ros.controller import ControllerNode
from experiment_runner.ros.node import JointStateOut, finite, warm_up_models
from experiment_runner.ros.run import run_node
from msg_defs.topics import PIEZOS, SAI_COMMAND
from stage_control.dither import dither_step


class DitherNode(ControllerNode):
    """Dither generator with harmonic cancelling: /stage/measured -> /stage/dither."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("dither_generator", **kwargs)
        self.pub = JointStateOut(self, "/stage/dither")
        self.subscribe_input(SAI_COMMAND, "sai", "effort")

    @classmethod
    def warm_up(cls):
        models = warm_up_models()
        dither_step(models.dither, models.initial_state([0.0]).dither, 0, *(np.zeros(1) for _ in range(3)),
                    np.zeros((2, 1)))

    def active(self, preset):
        return preset.dither is not None

    def build(self, preset):
        self.model = self.models.dither if preset.dither else None

    def reset(self):
        if self.model is not None:
            self.state = self.models.initial_state([self.tr.x_ref[0]]).dither
            self.out = np.zeros((2, 1))
            self.xr, self.vr, self.y = (np.zeros(1) for _ in range(3))       # one-trial inputs

    def healthy(self):
        return self.model is None or finite(self.out, self.state)

    def sample(self, k, got):
        if self.model is None:
            return
        self.xr[0] = self.tr.x_ref[k] + got.get("sai", 0.0)
        self.vr[0] = self.tr.v_ref[k]
        self.y[0] = got["measured"]
        dither_step(self.model, self.state, k, self.xr, self.vr, self.y, self.out)
        self.pub.publish(self.stamp(k), PIEZOS, effort=self.out[:, 0].tolist())

    def resend(self, k):
        if self.model is not None:
            self.pub.republish()


def main(args=None):
    run_node(DitherNode, args)
