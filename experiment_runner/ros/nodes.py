"""The nodes of the nanostage graph, listed once.

Every place that names a node reads this table: ``setup.py`` (one console script per
node, ``<name> = <module>:main``), the graph runner (:mod:`experiment_runner.ros.launch`
starts them in this order), the sequencer (it waits for the nodes that join runs and
names the missing ones), the nodes themselves (which node sent a lockstep input, to
name it in a fault) and the tests. The node name is also its executable's name.

Standard library only: ``setup.py`` executes this file on its own (no package import,
no rclpy).

Examples
--------
>>> [n.name for n in NODES][:2]
['plant_sim', 'servo_controller']
>>> publisher_of("/stage/command")
'servo_controller'
>>> console_scripts()[0]
'plant_sim = experiment_runner.ros.plant_node:main'
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["NodeSpec", "NODES", "NODE_NAMES", "JOINING", "node", "publisher_of", "console_scripts",
           "nodes_for"]


@dataclass(frozen=True)
class NodeSpec:
    """One node of the graph.

    Attributes
    ----------
    name : str
        Node name = name of its executable (console script).
    module : str
        Module of the ROS layer that holds the node class and its ``main``.
    cls : str
        The node class in ``module``.
    publishes : tuple of str
        Topics it publishes besides ``/experiment/events`` (every node reports there).
    needs : str or None
        Preset section without which the node has nothing to do (it still runs, idle).
    joins_runs : bool
        Subscribes ``/experiment/trajectory``: the sequencer waits for it before a run.
    """

    name: str
    module: str
    cls: str
    publishes: tuple[str, ...]
    needs: str | None = None
    joins_runs: bool = True


NODES: tuple[NodeSpec, ...] = (
    NodeSpec("plant_sim", "experiment_runner.ros.plant_node", "PlantNode",
             ("/stage/measured", "/stage/truth", "/clock", "/stage/isolator")),
    NodeSpec("servo_controller", "experiment_runner.ros.servo_node", "ServoNode",
             ("/stage/command", "/stage/reference")),
    NodeSpec("dither_generator", "experiment_runner.ros.dither_node", "DitherNode", ("/stage/dither",),
             needs="dither"),
    NodeSpec("sai_manager", "experiment_runner.ros.sai_node", "SaiNode", ("/sai/command", "/stage/correction"),
             needs="sai_manager"),
    NodeSpec("recorder", "experiment_runner.ros.recorder_node", "RecorderNode", ()),
    NodeSpec("experiment_sequencer", "experiment_runner.ros.sequencer_node", "SequencerNode",
             ("/experiment/config", "/experiment/trajectory", "/experiment/results"), joins_runs=False),
)
"""Every node, in start order (the recorder before the sequencer, which starts the run)."""

NODE_NAMES: tuple[str, ...] = tuple(n.name for n in NODES)
JOINING: tuple[str, ...] = tuple(n.name for n in NODES if n.joins_runs)
"""The nodes the sequencer waits for (subscribers of ``/experiment/trajectory``)."""


def node(name: str) -> NodeSpec:
    """The :class:`NodeSpec` of ``name`` (``KeyError`` names the known ones)."""
    for n in NODES:
        if n.name == name:
            return n
    raise KeyError(f"{name!r} is not a node of the graph; known: {', '.join(NODE_NAMES)}")


def publisher_of(topic: str) -> str:
    """The node that publishes ``topic`` (``"?"`` for a topic no node of the table publishes)."""
    for n in NODES:
        if topic in n.publishes:
            return n.name
    return "?"


def console_scripts() -> list[str]:
    """``setup.py`` entry points, one per node: ``"<name> = <module>:main"``."""
    return [f"{n.name} = {n.module}:main" for n in NODES]


def nodes_for(preset) -> tuple[str, ...]:
    """The nodes a run of ``preset`` needs (those whose preset section it has), in start order."""
    return tuple(n.name for n in NODES if n.needs is None or getattr(preset, n.needs, None) is not None)
