"""Presets of the seed stages (stage_sim/presets/*.yaml) and the loop-shaping PID design.

Checks: every preset validates; every value the seed tabulates round-trips (SI); the
loop-shaped PID gains equal ``loop_shape_pid`` and meet their bandwidth by
python-control; broken presets raise a ConfigError naming the field; every value in a
preset file carries a source comment.
"""
from __future__ import annotations

import doctest
import math
import re

import pytest
import yaml

from stage_control import tuning
from stage_sim import friction
from stage_control.tuning import closed_loop_bandwidth_hz, loop_shape_pid, margins
from stage_sim.config import PRESET_DIR, ConfigError, list_presets, load_preset, preset_from_dict, with_overrides

EXPECTED = {
    "als130h", "als130h_niasa", "van_sim", "van_sim_asym", "van_stage",
    "fi_stage_nofi", "fi_stage", "fi_stage_nofi_gms", "fi_stage_gms",
    "fi_stage_nofi_dob", "fi_stage_dob", "sai_stage",
    "sai_fi_ls_ld", "sai_fi_ls_hd", "sai_fi_hs_hd",
    "rotary_fi", "rotary_fi_nodamper", "rotary_nofi",
}

# Presets whose PID is derived with loop_shape_pid: (rigid gross-motion mass [kg], bandwidth [Hz]).
TUNED = {
    "van_stage": (2.0, 180.0),          # Sec. 3.3 (2 kg) / Sec. 3.4 (180 Hz)
    "fi_stage_nofi": (2.0, 200.0),      # Sec. 4.3
    "fi_stage": (2.0, 200.0),           # Sec. 4.3: same gains as No FI
    "fi_stage_nofi_gms": (2.0, 200.0),
    "fi_stage_gms": (2.0, 200.0),
    "fi_stage_nofi_dob": (2.0, 200.0),  # Sec. C.2.3: same PID
    "fi_stage_dob": (2.0, 200.0),
    "sai_stage": (1.4, 200.0),          # Sec. 5.2 (1.4 kg) / 5.3 (200 Hz)
    "sai_fi_ls_ld": (1.4, 200.0),       # Sec. 6.3.1: same PID as Ch. 5
    "sai_fi_ls_hd": (1.4, 200.0),
    "sai_fi_hs_hd": (1.4, 200.0),
}

TABLE_4_4_K = [1.34e6, 4.93e5, 8.61e4, 5.55e4, 5.87e4, 2.42e4, 3.85e4, 1.75e4, 2.69e4, 4.58e4]
TABLE_4_4_ALPHA = [0.0136, 0.0568, 0.037, 0.047, 0.0805, 0.0508, 0.1139, 0.0732, 0.1540, 0.3733]

approx = pytest.approx


def total_mass(p):
    """Rigid-body moving mass: table + appended mode masses + bearings."""
    st = p.stage
    return st.table.mass * (1 + sum(m.mass_ratio for m in st.modes)) + sum(b.mass for b in st.bearings)


def mode_peak_hz(mode):
    """Free-table FRF peak of an appended-mass mode."""
    return mode.frequency * math.sqrt(1 + mode.mass_ratio)


def dahl_totals(p):
    fr = [b.friction for b in p.stage.bearings]
    assert all(f.model == "dahl" for f in fr)
    return sum(f.k_sigma for f in fr), sum(f.f_c for f in fr)


# --------------------------------------------------------------------------- loading
def test_expected_presets_exist():
    assert EXPECTED <= set(list_presets())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_preset_loads_and_common_settings(name):
    p = load_preset(name)
    assert p.name == name
    assert p.description
    assert p.controller.rate == 10_000.0          # dSPACE 10 kHz (Sec. 3.4, 4.3, 5.3)
    assert p.simulation.seed == 0
    assert p.stage.drive.continuous_force <= p.stage.drive.peak_force


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_value_has_a_source_comment(name):
    """Each `key: value` / list item of a preset file carries a `# source` comment."""
    missing = []
    in_desc = False
    for i, line in enumerate((PRESET_DIR / f"{name}.yaml").read_text().splitlines(), 1):
        text = line.strip()
        if in_desc and line.startswith("  "):
            continue
        in_desc = text.startswith("description:")
        if not text or text.startswith("#") or text.startswith(("name:", "description:")):
            continue
        body = text[2:] if text.startswith("- ") else text
        m = re.match(r"^([A-Za-z_]\w*):\s*(.*)$", body)
        if m and (m.group(2) == "" or m.group(2).startswith("#")):
            continue                                # mapping/list header, no scalar value
        if " #" not in text:
            missing.append(f"line {i}: {text}")
    assert not missing, "values without a source comment:\n" + "\n".join(missing)


# --------------------------------------------------------------------------- Appendix A
def test_als130h_table_a1():
    p = load_preset("als130h")
    assert p.stage.table.mass == 1.5                       # Table A.1: m
    assert p.stage.bearings == [] and p.stage.modes == []
    tf = p.stage.table_friction
    assert (tf.model, tf.k_sigma, tf.f_c, tf.shape) == ("dahl", 8e6, 1.0, 1.0)   # k_sigma 8 N/um, F_C 1 N
    pid = p.controller.pid
    assert (pid.kp, pid.kd, pid.ki) == (8e5, 850.0, 0.0)  # K_P 0.8 N/um, K_D 8.5e-4 N s/um
    assert pid.derivative_cutoff is None                   # pure PD
    assert p.stage.encoder.resolution == 0.0
    assert p.stage.drive.noise_current_rms == 0.0
    # Table A.1's PD is itself a ~200 Hz loop on the rigid 1.5 kg stage
    assert closed_loop_bandwidth_hz(1.5, pid.model_dump()) == approx(200.0, rel=0.01)


def test_als130h_niasa_eq_a1():
    p = load_preset("als130h_niasa")
    n = p.controller.niasa
    assert (n.tau_d, n.k_sigma, n.f_c) == (0.004, 8e6, 1.0)   # Sec. A.2: tau_d = 4 ms
    assert p.controller.pid.ki == 0.0


# --------------------------------------------------------------------------- Ch. 3
def test_van_sim_sec_3_2_1():
    p = load_preset("van_sim")
    st = p.stage
    assert st.table.mass == 1.0 and [b.mass for b in st.bearings] == [0.25, 0.25]
    assert total_mass(p) == approx(1.5)                    # = Table A.1 m
    for b in st.bearings:
        assert (b.joint.stiffness, b.joint.damping) == (5e6, 20.0)   # 5 N/um, 2e-5 N s/um
    assert dahl_totals(p) == approx((8e6, 1.0))            # stage total = Table A.1
    pid = p.controller.pid
    assert (pid.kp, pid.kd, pid.ki) == (8e5, 850.0, 1e7)  # K_I = 10 N/(um s)
    d = p.dither
    assert (d.amplitude, d.frequency, d.hc_gain) == (3.0, 500.0, 0.0)
    assert sorted(b.dither_channel for b in st.bearings) == [0, 1]
    # "1% damping ratio" on the reduced table/bearing mass
    mu = 0.25 * 1.0 / 1.25
    assert 20.0 / (2 * math.sqrt(5e6 * mu)) == approx(0.01)


def test_van_sim_asym_sec_3_2_2():
    p = load_preset("van_sim_asym")
    j1, j2 = (b.joint for b in p.stage.bearings)
    assert (j1.stiffness, j1.damping) == (5e6, 20.0)
    assert j2.stiffness == approx(1.1 * j1.stiffness) == 5.5e6
    assert j2.damping == approx(1.1 * j1.damping) == 22.0
    assert p.dither.hc_gain == 4e9                        # K_HC = 4e3 N/um (Fig. 3.8b)
    assert (p.dither.amplitude, p.dither.frequency) == (3.0, 500.0)


def test_van_stage_sec_3_3():
    p = load_preset("van_stage")
    st = p.stage
    assert total_mass(p) == approx(2.0)                   # Sec. 3.3: 2 kg moving mass
    assert [b.joint.stiffness for b in st.bearings] == [6.9e6, 6.9e6]   # Table 3.1
    assert dahl_totals(p) == approx((2.19e6, 5.31))       # Table 4.3 (same stage)
    d = st.drive
    assert (d.force_constant, d.peak_force, d.continuous_force) == (11.0, 162.0, 23.0)
    assert st.encoder.resolution == 4.88e-9
    assert st.travel.max - st.travel.min == approx(0.05)   # 50 mm
    assert [mode_peak_hz(m) for m in st.modes] == [approx(560.0)]   # Fig. 3.12 yaw mode
    assert p.dither.frequency == 500.0
    assert 2 * p.dither.amplitude == 15.0                  # Sec. 3.4.1: 15 N peak-to-peak
    assert p.dither.hc_gain > 0
    assert sorted(b.dither_channel for b in st.bearings) == [0, 1]


# --------------------------------------------------------------------------- Ch. 4 / App. C
@pytest.mark.parametrize("name", ["fi_stage_nofi", "fi_stage", "fi_stage_nofi_gms", "fi_stage_gms",
                                  "fi_stage_nofi_dob", "fi_stage_dob"])
def test_fi_stage_family_common(name):
    p = load_preset(name)
    st = p.stage
    assert total_mass(p) == approx(2.0)                   # Sec. 3.3
    m_table = st.table.mass * (1 + sum(m.mass_ratio for m in st.modes))
    assert m_table / 2.0 == approx(7.9 / 13.8)            # Table C.1 Z ratio
    d = st.drive
    assert (d.force_constant, d.peak_force, d.continuous_force) == (11.0, 162.0, 23.0)
    assert st.encoder.resolution == 4.88e-9
    assert [mode_peak_hz(m) for m in st.modes] == [approx(400.0)]    # Fig. 4.4
    assert sum(b.friction.f_c for b in st.bearings) == approx(5.31)  # Table 4.3 F_C
    fi = "nofi" not in name
    if fi:
        assert sum(b.joint.stiffness for b in st.bearings) == approx(8.27e4)   # Table 4.3 k_fi
        assert st.bearing_sensor is not None
    else:
        assert all(b.joint is None for b in st.bearings)
    if name.endswith("_gms"):
        for b in st.bearings:
            assert b.friction.model == "gms"
            assert [2 * k for k in b.friction.k] == approx(TABLE_4_4_K)
            assert b.friction.alpha == approx(TABLE_4_4_ALPHA)
    else:
        assert dahl_totals(p) == approx((2.19e6, 5.31))    # Table 4.3 k_sigma,NoFI


def test_fi_stage_same_pid_as_nofi():
    nofi, fi = load_preset("fi_stage_nofi"), load_preset("fi_stage")
    assert fi.controller.pid == nofi.controller.pid       # Sec. 4.3: "exact same PID gains"
    assert [b.mass for b in fi.stage.bearings] == [b.mass for b in nofi.stage.bearings]
    assert fi.stage.table == nofi.stage.table


@pytest.mark.parametrize("name,Z,P,fq", [("fi_stage_dob", 13.8, 244.0, 200.0),
                                         ("fi_stage_nofi_dob", 7.9, 120.0, 100.0)])
def test_fi_dob_table_c1(name, Z, P, fq):
    dob = load_preset(name).controller.dob
    assert dob.gain * 11.0 == approx(Z)                    # Table C.1 Z [N/(A kg)] / K_f
    assert dob.pole == P and dob.q_cutoff == fq            # Table C.1 P; Sec. C.2.1/C.2.3 f_Q


# --------------------------------------------------------------------------- Ch. 5 / Ch. 6
def test_sai_stage_ch5():
    p = load_preset("sai_stage")
    st = p.stage
    assert total_mass(p) == approx(1.4)                   # Sec. 5.2
    (b,) = st.bearings
    assert b.joint.stiffness == 5e4                        # Table 5.1
    assert (b.friction.model, b.friction.k_sigma, b.friction.f_c) == ("dahl", 2.19e6, 5.31)  # Table 6.4
    assert st.encoder.resolution == 4.88e-9
    assert st.travel.max - st.travel.min == approx(0.025)  # 25 mm
    sai = st.sai
    assert sai.rc_cutoff == 300.0                          # Sec. 5.3
    assert sai.lock_stiffness > 10 * b.friction.k_sigma    # stiff mode >> k_f (Sec. 5.1)
    assert sai.lock_capacity > b.friction.f_c              # the lock holds the bearing friction
    assert 0 < sai.cushioning < 1
    m = p.sai_manager
    assert m.rule == "point_to_point"
    assert (m.ilc.iterations, m.ilc.cutoff, m.ilc.order) == (10, 200.0, 4)   # Eq. 5.2


@pytest.mark.parametrize("name,k,c", [("sai_fi_ls_ld", 3.3e4, 240.0), ("sai_fi_ls_hd", 2.9e4, 520.0),
                                      ("sai_fi_hs_hd", 6.8e4, 990.0)])
def test_sai_fi_table_6_2(name, k, c):
    p = load_preset(name)
    (b,) = p.stage.bearings
    assert (b.joint.stiffness, b.joint.damping) == (k, c)   # Table 6.2
    assert (b.friction.k_sigma, b.friction.f_c) == (2.19e6, 5.31)   # Table 6.4
    assert p.sai_manager.rule == "always_compliant"
    assert p.controller.feedforward is None                 # Sec. 6.3 P2P: no FF
    assert p.controller.pid == load_preset("sai_stage").controller.pid   # Sec. 6.3.1 same PID
    assert total_mass(p) == approx(1.4)


# --------------------------------------------------------------------------- Appendix D
@pytest.mark.parametrize("name,cf,fi", [("rotary_fi", 1.4, True), ("rotary_fi_nodamper", 0.2, True),
                                        ("rotary_nofi", 0.2, False)])
def test_rotary_tables_d1_d2(name, cf, fi):
    p = load_preset(name)
    st = p.stage
    assert st.kind == "rotary"
    assert st.table.mass == 0.1401                          # Table D.2 I_p
    assert [b.mass for b in st.bearings] == [0.01491, 0.01491]   # Table D.2 I_a (x2)
    for b in st.bearings:
        assert (b.friction.model, b.friction.f_c, b.friction.viscous) == ("coulomb", 0.0, cf)
        assert b.force_noise_rms == approx(0.15 * math.sqrt(2))     # Sec. D.4, correlated -> independent
        if fi:
            assert (b.joint.stiffness, b.joint.damping) == (324.85, 0.0)   # Table D.2
        else:
            assert b.joint is None
    pid = p.controller.pid
    assert (pid.kp, pid.kd, pid.ki) == (1.54e4, 81.62, 6.16e5)   # Table D.1
    assert 1 / (2 * math.pi * pid.derivative_cutoff) == approx(0.0005884)   # T_f
    inertia = 0.1401 + 2 * 0.01491
    dob = p.controller.dob
    assert dob.gain == approx(1 / inertia)                   # Eq. D.4 G_n
    assert dob.pole == approx(2 * cf / inertia)
    assert dob.q_cutoff == 80.0                              # Table D.1 f_Q
    assert st.encoder.resolution == 1.33e-6                  # Sec. D.3
    assert st.drive.noise_current_rms == 0.0


# --------------------------------------------------------------------------- tuned PID
@pytest.mark.parametrize("name", sorted(TUNED))
def test_tuned_pid_matches_loop_shape_pid(name):
    mass, bw = TUNED[name]
    p = load_preset(name)
    # the tuning mass is the preset's own rigid-body (gross-motion) moving mass
    assert total_mass(p) == approx(mass, rel=1e-9)
    expected = loop_shape_pid(mass, bw)
    got = p.controller.pid.model_dump()
    for key in ("kp", "ki", "kd", "derivative_cutoff"):
        assert got[key] == approx(expected[key], rel=1e-6), key
    assert closed_loop_bandwidth_hz(mass, got) == approx(bw, rel=0.02)
    m = margins(mass, got)
    assert m["phase_margin_deg"] > 35 and m["gain_margin_db"] > 10


# --------------------------------------------------------------------------- tuning module
@pytest.mark.parametrize("mass,bw", [(2.0, 200.0), (2.0, 180.0), (1.4, 200.0), (0.16992, 100.0)])
def test_loop_shape_pid_meets_bandwidth_and_shape(mass, bw):
    g = loop_shape_pid(mass, bw)
    assert closed_loop_bandwidth_hz(mass, g) == approx(bw, rel=0.01)
    m = margins(mass, g)                                     # half-sample Padé delay
    assert m["phase_margin_deg"] == approx(40.0, abs=0.01)
    wc = m["crossover_hz"]
    wd = 2 * math.pi * g["derivative_cutoff"]                # [rad/s]
    wz = 1.0 / (1.0 / wd + g["kd"] / g["kp"]) / (2 * math.pi)  # derivative (lead) zero [Hz]
    assert wz < wc < g["derivative_cutoff"]                  # lead: zero below, pole above crossover
    assert g["ki"] / g["kp"] / (2 * math.pi) == approx(wc / 5, rel=1e-6)
    # with a one-sample delay the margin drops by ~wc*Ts/2 more
    assert margins(mass, g, delay=1e-4)["phase_margin_deg"] < m["phase_margin_deg"]


def test_loop_shape_pid_rejects_bad_input():
    with pytest.raises(ValueError):
        loop_shape_pid(-1.0, 200.0)
    with pytest.raises(ValueError):
        loop_shape_pid(2.0, float("nan"))
    with pytest.raises(ValueError):
        loop_shape_pid(2.0, 200.0, phase_margin_deg=80.0, derivative_filter_ratio=2.0)


@pytest.mark.slow
def test_tuning_doctests():
    res = doctest.testmod(tuning)
    assert res.attempted > 0 and res.failed == 0


# --------------------------------------------------------------------------- broken presets
def _valid():
    return load_preset("fi_stage").model_dump()


@pytest.mark.parametrize("path,value,field,words", [
    (("stage", "table", "colour"), "red", "stage.table.colour", "unknown key"),
    (("stage", "table", "mass"), -1.0, "stage.table.mass", "greater than 0"),
    (("controller", "pid", "kp"), float("nan"), "controller.pid.kp", "finite"),
    (("stage", "bearings", 0, "joint", "stiffness"), float("nan"), "stage.bearings.0.joint.stiffness", "finite"),
])
def test_broken_preset_names_the_field(path, value, field, words):
    data = _valid()
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(ConfigError) as err:
        preset_from_dict(data, "broken")
    msg = str(err.value)
    assert field in msg and words in msg


@pytest.mark.parametrize("edit,field", [
    (lambda d: d["stage"]["table"].__setitem__("colour", "red"), "stage.table.colour"),
    (lambda d: d["stage"]["table"].__setitem__("mass", -2.0), "stage.table.mass"),
    (lambda d: d["controller"]["pid"].__setitem__("kd", float("nan")), "controller.pid.kd"),
])
def test_broken_preset_file_raises(tmp_path, edit, field):
    data = yaml.safe_load((PRESET_DIR / "sai_stage.yaml").read_text())
    edit(data)
    f = tmp_path / "broken.yaml"
    f.write_text(yaml.safe_dump(data))                       # NaN is written as .nan
    with pytest.raises(ConfigError) as err:
        load_preset(f)
    assert field in str(err.value) and str(f) in str(err.value)


# --------------------------------------------------------------------------- error messages, units, safe YAML
def _write(tmp_path, data, name="p.yaml"):
    f = tmp_path / name
    f.write_text(yaml.safe_dump(data, sort_keys=False))
    return f


def test_error_lines_name_file_field_value_and_what_is_allowed(tmp_path):
    data = yaml.safe_load((PRESET_DIR / "fi_stage.yaml").read_text())
    data["stage"]["table"]["mass"] = -1
    data["stage"]["table"]["mas"] = 3
    del data["stage"]["drive"]["peak_force"]
    data["stage"]["bearings"][0]["friction"]["model"] = "dahll"
    data["controller"]["pid"]["kp"] = True
    f = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_preset(f)
    lines = str(err.value).splitlines()
    assert lines[0] == f"{f}: invalid preset"
    assert set(lines[1:]) == {
        "  stage.table.mass: got -1; expected greater than 0 -- moving table mass [kg] (rotary: inertia [kg·m²])",
        "  stage.table.mas: unknown key (got 3); allowed keys: mass",
        "  stage.bearings.0.friction.model: got 'dahll'; expected one of "      # every law of the registry
        + ", ".join(repr(law.NAME) for law in friction.LAWS),
        "  stage.drive.peak_force: required field is missing -- peak force limit [N]",
        "  controller.pid.kp: expected a number, not true/false (got True)",
    }
    assert {p.path for p in err.value.problems} == {"stage.table.mass", "stage.table.mas", "stage.drive.peak_force",
                                                    "stage.bearings.0.friction.model", "controller.pid.kp"}


def test_a_stiffness_in_n_per_um_is_refused_as_likely_the_wrong_unit(tmp_path):
    data = yaml.safe_load((PRESET_DIR / "fi_stage.yaml").read_text())
    data["stage"]["bearings"][0]["joint"]["stiffness"] = 0.04135          # 4.135e4 N/m written in N/µm
    data["stage"]["table"]["mass"] = 1040.8                               # 1.0408 kg written in g
    f = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_preset(f)
    msg = str(err.value)
    assert msg.startswith(f"{f}: implausible value(s) (a wrong unit?)")
    assert ("  stage.bearings.0.joint.stiffness: got 0.04135 N/m, outside the plausible range 1 to 1e+10 N/m; "
            "likely given in N/mm (0.04135 N/mm = 41.35 N/m) or N/µm (0.04135 N/µm = 4.135e+04 N/m) "
            "instead of N/m") in msg
    assert "  stage.table.mass: got 1040.8 kg, outside the plausible range 0.0001 to 1000 kg; likely given in g" in msg
    assert "plausibility: warn" in msg
    # a deliberate value: the file says so, and loads with a warning naming the field
    data["plausibility"] = "warn"
    with pytest.warns(UserWarning, match="stage.bearings.0.joint.stiffness: got 0.04135"):
        p = load_preset(_write(tmp_path, data, "warn.yaml"))
    assert p.stage.bearings[0].joint.stiffness == 0.04135
    data["plausibility"] = "off"
    load_preset(_write(tmp_path, data, "off.yaml"))


def test_a_rotary_stage_has_rotary_ranges_and_rotary_unit_messages(tmp_path):
    """A small rotary servo: a viscous coefficient of 1e-4 N·m·s/rad, a pre-sliding (Dahl)
    stiffness of 1 N·m/rad, a 0.02 N·m Coulomb torque, a rotor of 2e-6 kg·m² -- values a linear
    stage would not have -- load on a rotary preset; the same values on a linear preset are
    refused; what is still implausible on a rotary stage is said in rotary units."""
    data = yaml.safe_load((PRESET_DIR / "rotary_nofi.yaml").read_text())
    data["stage"]["table"]["mass"] = 2e-6
    for b in data["stage"]["bearings"]:
        b["mass"] = 1e-7
        b["force_noise_rms"] = 0.0
        b["friction"] = {"model": "dahl", "k_sigma": 1.0, "f_c": 0.02, "viscous": 1e-4}
    p = load_preset(_write(tmp_path, data, "servo.yaml"))
    assert p.stage.kind == "rotary" and p.stage.bearings[0].friction.viscous == 1e-4
    assert p.stage.bearings[0].friction.k_sigma == 1.0
    linear = dict(data, stage=dict(data["stage"], kind="linear"))
    with pytest.raises(ConfigError) as err:
        load_preset(_write(tmp_path, linear, "lin.yaml"))
    assert "stage.bearings.0.friction.viscous: got 0.0001 N·s/m, outside the plausible range 0.001 to 100000 N·s/m" \
        in str(err.value)
    # a rotary value off by a unit: rotary ranges, rotary units, rotary hints
    data["stage"]["bearings"][0]["friction"]["viscous"] = 2e6        # 2 N·m·s/rad written in N·mm·s/rad
    data["stage"]["table"]["mass"] = 3000.0                          # 0.3 kg·m² written in kg·cm²
    with pytest.raises(ConfigError) as err:
        load_preset(_write(tmp_path, data, "bad.yaml"))
    msg = str(err.value)
    assert ("  stage.bearings.0.friction.viscous: got 2e+06 N·m·s/rad, outside the plausible range 1e-09 to 100000 "
            "N·m·s/rad; likely given in N·mm·s/rad (2e+06 N·mm·s/rad = 2000 N·m·s/rad)") in msg
    assert ("  stage.table.mass: got 3000 kg·m², outside the plausible range 1e-10 to 1000 kg·m²; likely given in "
            "kg·cm² (3000 kg·cm² = 0.3 kg·m²)") in msg
    assert "N/m" not in msg and "N·s/m" not in msg and " kg," not in msg
    # a schema error on a rotary stage names the rotary unit
    data["stage"]["table"]["mass"] = -1
    with pytest.raises(ConfigError, match=r"stage.table.mass: got -1; expected greater than 0 -- moving table "
                                          r"mass \[kg·m²\]"):
        load_preset(_write(tmp_path, data, "neg.yaml"))


def test_overrides_are_checked_and_a_wrong_path_is_named():
    p = load_preset("fi_stage")
    with pytest.raises(ConfigError, match=r"^exp.yaml: implausible.*\n  controller.pid.kp: got 0.8 N/m.*N/µm"):
        with_overrides(p, {"controller.pid.kp": 0.8}, "exp.yaml")
    with pytest.raises(ConfigError, match=r"^exp.yaml: override 'stage.tabel.mass': stage has no field 'tabel' "
                                          r"\(fields: kind, table, "):
        with_overrides(p, {"stage.tabel.mass": 1.0}, "exp.yaml")
    with pytest.raises(ConfigError, match=r"override 'stage.bearings.7.mass': stage.bearings has 2 item\(s\), "
                                          r"no item '7'"):
        with_overrides(p, {"stage.bearings.7.mass": 1.0}, "exp.yaml")


def test_yaml_is_loaded_safely_and_duplicate_keys_are_refused(tmp_path):
    text = (PRESET_DIR / "fi_stage.yaml").read_text()
    f = tmp_path / "dup.yaml"
    f.write_text(text.replace("name: fi_stage\n", "name: fi_stage\nname: other\n", 1))
    with pytest.raises(ConfigError, match=rf"^{f}: not valid YAML at line 9, column 1: "
                                          r"found duplicate key 'name' \(first at line 8\)"):
        load_preset(f)
    marker = tmp_path / "executed"
    f.write_text(f"!!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ConfigError, match=rf"^{f}: not valid YAML at line 1, column 1: could not determine a "
                                          "constructor for the tag 'tag:yaml.org,2002:python/object/apply:os.system'"):
        load_preset(f)
    assert not marker.exists()
    f.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match=rf"^{f}: not valid YAML at line 2, column 1: "):
        load_preset(f)
    f.write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(ConfigError, match=rf"{f}: not UTF-8 text \(byte 0: b'\\xff'\)"):
        load_preset(f)


# --------------------------------------------------------------------------- node parameter files
def _run_node(node: str, pfile, values: dict, domain: int):
    """Start a node executable with a params file on ``domain``; (exit code, stderr)."""
    import subprocess
    import sys
    from pathlib import Path

    from experiment_runner.ros.run import domain_env
    pfile.write_text(yaml.safe_dump({node: {"ros__parameters": values}}))
    env = domain_env(domain)
    proc = subprocess.run([str(Path(sys.executable).parent / node), "--ros-args", "--params-file", str(pfile)],
                          env=env, capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stderr


@pytest.mark.ros
def test_node_parameter_files_are_checked_like_every_other_file(tmp_path, ros_domain):
    code, err = _run_node("plant_sim", tmp_path / "typo.yaml", {"input_timeot": 2.0}, ros_domain)
    assert code == 2 and "Traceback" not in err
    assert f"error: plant_sim (params file {tmp_path / 'typo.yaml'}): invalid parameters\n" in err
    assert "  input_timeot: unknown parameter (got 2.0); allowed: " in err and "input_timeout" in err.split("allowed:")[1]
    code, err = _run_node("plant_sim", tmp_path / "neg.yaml", {"input_timeout": -1.0}, ros_domain)
    assert code == 2 and ("  input_timeout: got -1.0; expected a number from 0.01 to 3600.0 -- wall-clock time "
                          "to wait for a sample's inputs") in err
    bad = tmp_path / "bad_preset.yaml"
    data = yaml.safe_load((PRESET_DIR / "fi_stage.yaml").read_text())
    data["stage"]["bearings"][0]["joint"]["stiffness"] = 0.04135
    bad.write_text(yaml.safe_dump(data))
    code, err = _run_node("plant_sim", tmp_path / "preset.yaml", {"preset": str(bad)}, ros_domain)
    # the value is shown shortened where it is long (a deep temporary path under pytest -n): its head, then the file
    assert code == 2 and f"  preset: got '{str(bad)[:40]}" in err and f"; {bad}: implausible value(s)" in err
    assert "stage.bearings.0.joint.stiffness: got 0.04135 N/m" in err and "N/µm" in err


def test_a_node_started_by_hand_defaults_to_a_local_graph_on_an_explicit_domain():
    from experiment_runner.ros.run import GRAPH_DEFAULTS, apply_graph_defaults, loopback_env
    env = {}
    assert apply_graph_defaults(env) == env == {**GRAPH_DEFAULTS, **loopback_env(GRAPH_DEFAULTS)}  # test_network.py
    env = {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}      # opened on purpose
    assert apply_graph_defaults(env) == {} and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    env = {"ROS_LOCALHOST_ONLY": "0"}
    assert apply_graph_defaults(env) == {"ROS_DOMAIN_ID": "42"}
