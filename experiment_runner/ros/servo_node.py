"""``servo_controller`` node: PID / DOB / feedforward / NIASA servo of the stage.

Lockstep: for each control sample, once ``/stage/measured`` (and, on SAI stages, the SAI
manager's reference correction on ``/sai/command``) is in, one call of
:func:`stage_control.servo.servo_step` gives the drive command, published on
``/stage/command`` with the reference used on ``/stage/reference``. The command is
saturated at the drive's peak force (:func:`stage_control.servo.build_servo`); a
reference outside the stage's travel is refused before the trial starts
(``reference_out_of_travel`` fault naming the sequencer). Shared trial bookkeeping and
fault handling: :mod:`experiment_runner.ros.controller`.
"""
from __future__ import annotations

import numpy as np

from experiment_runner.ros.controller import ControllerNode
from experiment_runner.ros.node import JointStateOut, finite, warm_up_models
from experiment_runner.ros.run import run_node
from msg_defs.topics import SAI_COMMAND
from stage_control.servo import check_reference, servo_step

MOTOR, TABLE = ("motor",), ("table",)


class ServoNode(ControllerNode):
    """PID / DOB / feedforward / NIASA servo: /stage/measured -> /stage/command, /stage/reference."""

    inputs = ("measured", "sai")

    def __init__(self, **kwargs):
        super().__init__("servo_controller", **kwargs)
        self.pub_command = JointStateOut(self, "/stage/command")
        self.pub_reference = JointStateOut(self, "/stage/reference")
        self.subscribe_samples(SAI_COMMAND, lambda stamp, n, p, v, e: self._put(stamp, "sai", e[0]))

    @classmethod
    def warm_up(cls):
        models = warm_up_models()
        servo_step(models.servo, models.initial_state([0.0]).servo, *(np.zeros(1) for _ in range(4)))

    def build(self, preset):
        self.model = self.models.servo

    def reset(self):
        self.state = self.models.initial_state([self.tr.x_ref[0]]).servo
        self.u, self.xr, self.vr, self.y = (np.zeros(1) for _ in range(4))   # one-trial inputs and output

    def refuse(self, tr):
        problem = check_reference(tr.x_ref, self.preset.stage.travel)
        return problem and ("reference_out_of_travel", f"trial {tr.trial} refused: {problem}",
                            "experiment_sequencer")

    def healthy(self):
        return finite(self.u, self.state)

    def sample(self, k, got):
        xr, vr = self.xr, self.vr
        xr[0] = x = self.tr.x_ref[k] + got.get("sai", 0.0)
        vr[0] = v = self.tr.v_ref[k]
        self.y[0] = got["measured"]
        servo_step(self.model, self.state, xr, vr, self.y, self.u)
        stamp = self.stamp(k)
        self.pub_command.publish(stamp, MOTOR, effort=(self.u[0],))
        self.pub_reference.publish(stamp, TABLE, position=(x,), velocity=(v,))

    def resend(self, k):
        self.pub_command.republish()
        self.pub_reference.republish()


def main(args=None):
    run_node(ServoNode, args)
