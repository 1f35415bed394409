"""The ROS 2 layer: the only code that imports rclpy (enforced: ``.importlinter``).

Thin nodes around the ROS-free core: each node converts messages to the arrays the
core's compiled step functions take and back; no algorithm lives here. One node per
module:

- ``plant_node``: ``plant_sim`` around :func:`stage_sim.plant.plant_step`;
- ``servo_node``: ``servo_controller`` around :func:`stage_control.servo.servo_step`;
- ``dither_node``: ``dither_generator`` around :func:`stage_control.dither.dither_step`;
- ``sai_node``: ``sai_manager`` around :func:`stage_control.sai.sai_step` and the ILC;
- ``sequencer_node``: ``experiment_sequencer`` (trials of :mod:`experiment_runner.core.experiment`);
- ``recorder_node``: ``recorder`` (MCAP through :mod:`experiment_runner.core.recording`).

What they share: ``nodes`` (the table of nodes, read by ``setup.py``, the launcher, the
sequencer and the tests), ``node`` (base class: topics, parameters, fault injection,
lockstep), ``controller`` (base of the three controller nodes), ``run`` (a node
executable's ``main``, executors, graph environment), ``qos`` (rclpy QoS of the contract
topics). Around them: ``launch`` (the graph in one process, or one process per node),
``player`` (republish a recording) and ``timing`` (middleware and graph-loop timing).

Below this layer, the core (``stage_sim``, ``stage_control``, ``msg_defs``, and the batch
engine, profiles, metrics, experiments and recordings of ``experiment_runner``) imports
no rclpy and nothing from here; above it, the applications (``nanostage graph``,
``replay``, ``bench``, campaigns) use it.
"""
