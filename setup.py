"""ament_python package ``nanostage`` (also installable with plain pip)."""
import runpy
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "nanostage"
MODULES = ["stage_sim", "stage_control", "experiment_runner", "msg_defs"]
# one console script per node of the graph, from the one table of nodes (standard library only)
NODE_SCRIPTS = runpy.run_path(str(Path(__file__).parent / "experiment_runner" / "ros" / "nodes.py"))["console_scripts"]()

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[p for m in MODULES for p in (m, f"{m}.*")]),
    # the data files beside the modules (presets, experiments, campaigns, nominal models, mappings, the
    # Fast DDS profile): every package's *.yaml / *.xml and those of its data folders, whatever the layout
    package_data={"": ["*.yaml", "*.xml", "*/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/presets", glob("stage_sim/presets/*.yaml")),
        (f"share/{PACKAGE}/experiments", glob("experiment_runner/core/experiments/*.yaml")),
        (f"share/{PACKAGE}/campaigns", glob("experiment_runner/apps/campaigns/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="nanostage developers",
    maintainer_email="nanostage@example.com",
    description="Nanopositioning stages with pre-motion friction: simulation, control, experiments.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "nanostage = experiment_runner.apps.cli:main",
            *NODE_SCRIPTS,
        ],
    },
)
