"""The suite's own rules (``conftest.py``): the fast tier and the core suite start no DDS, markers
follow the fixtures a test uses, graphs of tests never share a ROS domain."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import DOMAINS, lease_domain

BIN = Path(sys.executable).parent


def test_a_test_without_the_ros_marker_cannot_start_dds():
    """An rclpy context made, or a node process started, by a test without ``@pytest.mark.ros``
    fails that test, naming the marker (the fast tier would otherwise start DDS unnoticed)."""
    from rclpy.context import Context
    with pytest.raises(AssertionError, match=r"test_suite\.py::.* initialises an rclpy context but is not marked "
                                             r"@pytest\.mark\.ros"):
        Context().init()
    with pytest.raises(AssertionError, match=r"starts the node process .*plant_sim but is not marked"):
        subprocess.Popen([str(BIN / "plant_sim"), "--ros-args"])
    out = subprocess.run([sys.executable, "-c", "print(1)"], capture_output=True, text=True, timeout=60)
    assert out.stdout == "1\n"                                         # any other process starts


def test_markers_follow_the_fixtures(request, shared_data):
    """A test using the shared data is ``realdata`` without saying so (``-m "not realdata"``
    deselects it)."""
    assert request.node.get_closest_marker("realdata") is not None
    assert request.node.get_closest_marker("ros") is None and request.node.get_closest_marker("slow") is None


@pytest.mark.ros
def test_ros_tests_are_slow_too(request):
    """The fast tier (``-m "not slow"``) deselects every ``ros`` test."""
    assert request.node.get_closest_marker("slow") is not None


def test_each_lease_is_a_domain_no_other_lease_holds():
    with lease_domain() as a, lease_domain() as b:
        assert a != b and a in DOMAINS and b in DOMAINS
        code = ("import sys; sys.path.insert(0, 'test'); from conftest import lease_domain\n"
                "with lease_domain() as d: print(d)")
        other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                               cwd=Path(__file__).parents[1])
        assert other.returncode == 0, other.stderr
        assert int(other.stdout) not in (a, b)                 # another process (an xdist worker, a checkout)
