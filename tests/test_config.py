"""Config: frozen dataclasses from TOML scenarios, `extends`, "none", overrides and errors."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from conftest import REPO

from pipeline.config import (
    ConfigError,
    RunConfig,
    config_hash,
    impact_time_bounds_s,
    load_config,
    scenario_path,
    to_dict,
    validate_run_id,
)
from pipeline.config.checks import MAX_FRAMES
from pipeline.workspace import workspace


def write_scenario(name: str, text: str) -> Path:
    """A scenario file in the working directory's runs/scenarios/ (use with `workdir`)."""
    path = Path("runs/scenarios") / f"{name}.toml"
    path.write_text(text)
    return path


def default_with(section: str, key: str, value: str) -> str:
    """default.toml with `key = value` replaced in [section] ('' for the top level)."""
    lines = Path("runs/scenarios/default.toml").read_text().splitlines()
    current, out, done = "", [], False
    for line in lines:
        stripped = line.strip()
        if stripped.startswith("["):
            current = stripped.split("#")[0].strip().strip("[]")
        if current == section and stripped.split("=")[0].strip() == key and not done:
            line, done = f"{key} = {value}", True
        out.append(line)
    assert done, (section, key)
    return "\n".join(out) + "\n"


def sections(cfg: RunConfig) -> dict[str, object]:
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)
            if dataclasses.is_dataclass(getattr(cfg, f.name))}


def test_default_scenario_loads(workdir):
    cfg = load_config("default")
    assert (cfg.name, cfg.run_id) == ("default", "default")
    assert cfg.catalogue.source == "synthetic"
    assert cfg.catalogue.healpix_order == 6
    assert cfg.catalogue.max_reject_share is None  # "none"
    assert cfg.trajectory.end_s is None
    assert cfg.sweep.caps[-1] is None and cfg.sweep.caps[0] == 10
    assert cfg.detection.fov_deg == 45.0 and isinstance(cfg.detection.fov_deg, float)
    assert [w.name for w in cfg.scoring.windows] == ["0-1500 s", "1500-2850 s", "1800-2400 s"]
    assert load_config("default", run_id="other").run_id == "other"


def test_default_toml_lists_every_key(workdir):
    """default.toml is complete: every dataclass field of every section is in the file."""
    data = tomllib.loads(Path("runs/scenarios/default.toml").read_text())
    for name, section in sections(load_config("default")).items():
        fields = {f.name for f in dataclasses.fields(section)}
        assert fields == set(data[name]), name


def test_every_stage_section_is_a_frozen_dataclass(workdir):
    cfg = load_config("default")
    found = sections(cfg)
    assert {"catalogue", "trajectory", "detection", "estimation", "scoring", "sweep"} <= set(found)
    for name, section in [("run", cfg), *found.items(), ("window", cfg.scoring.windows[0])]:
        assert type(section).__dataclass_params__.frozen, name
        first = dataclasses.fields(section)[0].name
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(section, first, None)
    # sequences are tuples, so nothing inside the config can be mutated either
    assert isinstance(cfg.estimation.methods, tuple)
    assert isinstance(cfg.scoring.windows, tuple)
    assert isinstance(cfg.trajectory.specific_force_body_m_s2, tuple)


@pytest.mark.parametrize(("text", "key"), [
    ('extends = "default"\nbogus_top = 1\n', "bogus_top"),
    ('extends = "default"\n[catalogue]\nhealpix_oder = 5\n', "healpix_oder"),
    ('extends = "default"\n[detection]\nfov = 30.0\n', "fov"),
    ('extends = "default"\n[nosuchsection]\nx = 1\n', "nosuchsection"),
    ('extends = "default"\n[[scoring.windows]]\nname = "a"\nstart_s = 0.0\nend_s = 1.0\n'
     'colour = "red"\n', "colour"),
])
def test_unknown_key_names_file_and_key(workdir, text, key):
    path = write_scenario("typo", text)
    with pytest.raises(ConfigError) as exc:
        load_config("typo")
    assert str(path) in str(exc.value)
    assert key in str(exc.value)


def test_unknown_key_in_parent_names_the_parent_file(workdir):
    write_scenario("parent", 'extends = "default"\n[catalogue]\nbogus = 1\n')
    write_scenario("child", 'extends = "parent"\n')
    with pytest.raises(ConfigError, match=r"parent\.toml"):
        load_config("child")


@pytest.mark.parametrize(("section", "key", "value", "full_key"), [
    ("catalogue", "healpix_order", '"six"', "catalogue.healpix_order"),
    ("catalogue", "healpix_order", "6.5", "catalogue.healpix_order"),
    ("catalogue", "healpix_order", "true", "catalogue.healpix_order"),
    ("catalogue", "source", "3", "catalogue.source"),
    ("detection", "fov_deg", '"wide"', "detection.fov_deg"),
    ("detection", "fov_deg", '"none"', "detection.fov_deg"),  # not optional
    ("estimation", "robust", "1", "estimation.robust"),
    ("estimation", "methods", '"paper"', "estimation.methods"),
    ("trajectory", "specific_force_body_m_s2", '[0.0, "x", 0.0]',
     "trajectory.specific_force_body_m_s2[1]"),
    ("sweep", "caps", '[10, "lots"]', "sweep.caps[1]"),
], ids=lambda v: v if isinstance(v, str) and "." in v else None)
def test_wrong_type_names_the_key(workdir, section, key, value, full_key):
    path = write_scenario("bad", default_with(section, key, value))
    with pytest.raises(ConfigError) as exc:
        load_config("bad")
    assert full_key in str(exc.value) and str(path) in str(exc.value)


@pytest.mark.parametrize(("section", "key", "value", "full_key"), [
    ("catalogue", "healpix_order", "13", "catalogue.healpix_order"),
    ("catalogue", "healpix_order", "-1", "catalogue.healpix_order"),
    ("catalogue", "max_reject_share", "1.5", "catalogue.max_reject_share"),
    ("catalogue", "synthetic_min_diam_km", "0.0", "catalogue.synthetic_min_diam_km"),
    ("catalogue", "synthetic_min_diam_km", "400.0", "catalogue.synthetic_min_diam_km"),
    ("detection", "fov_deg", "90.0", "detection.fov_deg"),
    ("detection", "p_identify", "1.01", "detection.p_identify"),
    ("detection", "selection", '"best"', "detection.selection"),
    ("detection", "max_craters", "0", "detection.max_craters"),
    ("estimation", "methods", '["paper", "magic"]', "estimation.methods"),
    ("scoring", "table_window", '"0-10 s"', "scoring.table_window"),
    ("trajectory", "end_s", "-5.0", "trajectory.end_s"),
    ("render", "albedo", "0.5", "render.albedo"),
    ("identification", "mode", '"psychic"', "identification.mode"),
    ("imu.gyro", "bias_correlation_s", "1e-300", "imu.gyro.bias_correlation_s"),  # white
], ids=lambda v: v if isinstance(v, str) and "." in v else None)
def test_out_of_range_names_the_key(workdir, section, key, value, full_key):
    path = write_scenario("bad", default_with(section, key, value))
    with pytest.raises(ConfigError, match=full_key.replace(".", r"\.")) as exc:
        load_config("bad")
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_negative_generator_seed_is_a_config_error(workdir):
    write_scenario("bad", default_with("catalogue", "seed", "-1"))
    with pytest.raises(ConfigError, match=r"catalogue\.seed"):
        load_config("bad")


def test_run_id_and_name_are_not_scenario_keys(workdir):
    """run_id and name come from the command line and the file name, never from the file (the
    old test accepted either outcome and so could not fail)."""
    path = write_scenario("rid", 'extends = "default"\nrun_id = "elsewhere"\nname = "other"\n')
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['name', 'run_id'\]") as exc:
        load_config("rid", run_id="mine")
    assert str(path) in str(exc.value)
    write_scenario("rid", 'extends = "default"\n')
    cfg = load_config("rid", run_id="mine")
    assert (cfg.name, cfg.run_id) == ("rid", "mine")


def test_none_string_means_none_for_optional_fields(workdir):
    write_scenario("nones", 'extends = "default"\n[catalogue]\nmax_reject_share = "None"\n'
                   '[detection]\nmax_craters = "NONE"\n[trajectory]\nend_s = 100.0\n'
                   '[sweep]\ncaps = ["none", 5]\n')
    cfg = load_config("nones")
    assert cfg.catalogue.max_reject_share is None
    assert cfg.detection.max_craters is None
    assert cfg.trajectory.end_s == 100.0
    assert cfg.sweep.caps == (None, 5)
    assert json.loads(json.dumps(to_dict(cfg)))["detection"]["max_craters"] is None


def test_extends_merges_tables_and_chains(workdir):
    write_scenario("child", 'extends = "default"\nseed = 5\n[catalogue]\nhealpix_order = 4\n'
                   '[[scoring.windows]]\nname = "all"\nstart_s = 0.0\nend_s = 3000.0\n'
                   '[scoring]\ntable_window = "all"\n')
    write_scenario("grandchild", 'extends = "child"\n[catalogue]\nseed = 9\n')
    base, child, grand = load_config("default"), load_config("child"), load_config("grandchild")
    assert (child.name, child.seed, child.catalogue.healpix_order) == ("child", 5, 4)
    assert child.catalogue.db_path == base.catalogue.db_path  # untouched keys inherited
    assert child.detection == base.detection
    assert [w.name for w in child.scoring.windows] == ["all"]  # arrays replace, not append
    assert (grand.seed, grand.catalogue.healpix_order, grand.catalogue.seed) == (5, 4, 9)
    assert grand.catalogue.synthetic_max_diam_km == base.catalogue.synthetic_max_diam_km


def test_extends_cycle_and_missing_parent_are_errors(workdir):
    write_scenario("a", 'extends = "b"\n')
    write_scenario("b", 'extends = "a"\n')
    with pytest.raises(ConfigError, match="cycle"):
        load_config("a")
    write_scenario("orphan", 'extends = "nope"\n')
    with pytest.raises(ConfigError, match="nope"):
        load_config("orphan")


def test_missing_scenario_and_bad_toml_name_the_file(workdir):
    with pytest.raises(ConfigError, match=r"absent\.toml.*not found"):
        load_config("absent")
    path = write_scenario("broken", "[catalogue\nseed = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML") as exc:
        load_config("broken")
    assert str(path) in str(exc.value)


def test_missing_key_without_extends_is_an_error(workdir):
    text = default_with("catalogue", "seed", "1").replace("seed = 1\n", "", 2)
    write_scenario("partial", text)
    with pytest.raises(ConfigError, match=r"missing key\(s\) \['seed'\]"):
        load_config("partial")


def test_overrides_merge_over_the_file_and_are_validated(workdir):
    write_scenario("child", 'extends = "default"\n[catalogue]\nhealpix_order = 4\n')
    cfg = load_config("child", overrides={"catalogue": {"source": "x.csv", "format": "head2010"}})
    assert (cfg.catalogue.source, cfg.catalogue.format) == ("x.csv", "head2010")
    assert cfg.catalogue.healpix_order == 4 and cfg.catalogue.seed == 2018
    with pytest.raises(ConfigError, match=r"catalogue\.healpix_order"):
        load_config("default", overrides={"catalogue": {"healpix_order": 20}})
    with pytest.raises(ConfigError, match="nope"):
        load_config("default", overrides={"catalogue": {"nope": 1}})


def test_scenario_given_as_a_toml_path(workdir):
    path = write_scenario("elsewhere", 'extends = "default"\nseed = 3\n')
    cfg = load_config(str(path.resolve()))
    assert (cfg.name, cfg.seed) == ("elsewhere", 3)


# --- config_hash ----------------------------------------------------------------------------------


def test_config_hash_is_stable(workdir):
    a, b = load_config("default"), load_config("default")
    assert config_hash(a.catalogue) == config_hash(b.catalogue)
    assert len(config_hash(a)) == 16 and int(config_hash(a), 16) >= 0
    assert config_hash({"x": 1, "y": [1, 2]}) == config_hash({"y": [1, 2], "x": 1})


def test_config_hash_is_the_same_in_another_process(workdir):
    """No dependence on Python's per-process hash randomisation or on memory addresses."""
    code = ("from pipeline.config import load_config, config_hash; "
            "c = load_config('default'); print(config_hash('ingest', c.catalogue, c.scoring))")
    outs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           check=True, cwd=workdir,
                           env={**os.environ, "PYTHONHASHSEED": seed, "PYTHONPATH": str(REPO)}
                           ).stdout.strip() for seed in ("1", "2")}
    c = load_config("default")
    assert outs == {config_hash("ingest", c.catalogue, c.scoring)}


@pytest.mark.parametrize(("section", "key", "value"), [
    ("catalogue", "seed", 2019),
    ("catalogue", "healpix_order", 7),
    ("catalogue", "source", "other.csv"),
    ("catalogue", "max_reject_share", 0.05),
    ("catalogue", "synthetic_min_diam_km", 1.0 + 1e-12),
    ("detection", "max_craters", 10),
    ("scoring", "final_window_s", 151.0),
])
def test_config_hash_changes_with_any_value(workdir, section, key, value):
    base = load_config("default")
    changed = load_config("default", overrides={section: {key: value}})
    assert getattr(getattr(changed, section), key) == value
    assert config_hash(getattr(changed, section)) != config_hash(getattr(base, section))
    assert config_hash(changed) != config_hash(base)


def test_config_hash_distinguishes_none_and_parts(workdir):
    cfg = load_config("default")
    assert config_hash("ingest", cfg.catalogue) != config_hash("detect", cfg.catalogue)
    assert config_hash(None) != config_hash("none")
    assert config_hash(cfg.catalogue, "a") != config_hash(cfg.catalogue, "b")


# --- validation at the door: every numeric field, then impossible combinations -------------------

SECTION_CLASSES = {"": "RunConfig", "catalogue": "CatalogueConfig",
                   "trajectory": "TrajectoryConfig", "detection": "DetectionConfig",
                   "estimation": "EstimationConfig", "scoring": "ScoringConfig",
                   "scoring.windows": "Window", "sweep": "SweepConfig"}


def _numeric_cases() -> list[tuple[str, str, str]]:
    """(section, key, TOML value) of a bad value for every numeric field of every section:
    nan, inf, -inf and an absurd 1e300 for each float, -1 and 1e18 for each int (1e18 is a valid
    seed), a non-finite component for float lists, a bad item for int lists."""
    import typing

    from pipeline import config

    cases = []
    for section, cls_name in SECTION_CLASSES.items():
        cls = getattr(config, cls_name)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if cls is RunConfig and f.name in ("name", "run_id"):
                continue
            tp = hints[f.name]
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if typing.get_origin(tp) is tuple:
                item = typing.get_args(tp)[0]
                item_args = [a for a in typing.get_args(item) if a is not type(None)] or [item]
                if item_args[0] is float:
                    cases += [(section, f.name, f"[{v}, 0.0, 0.0]") for v in ("nan", "inf")]
                elif item_args[0] is int:
                    cases += [(section, f.name, "[-1]"), (section, f.name, "[1_000_000_000]")]
                    if f.name == "seeds":
                        cases.pop()
                elif item_args[0] is str:
                    cases.append((section, f.name, "[]"))
                continue
            base = args[0] if args else tp
            if base is float:
                cases += [(section, f.name, v) for v in ("nan", "inf", "-inf", "1e300")]
            elif base is int:
                cases.append((section, f.name, "-1"))
                if "seed" not in f.name:
                    cases.append((section, f.name, "1_000_000_000_000_000_000"))
    return cases


@pytest.mark.parametrize(("section", "key", "value"), _numeric_cases(),
                         ids=lambda v: v.replace(".", "_") if isinstance(v, str) else None)
def test_every_numeric_field_refuses_non_finite_and_absurd_values(workdir, section, key, value):
    """Each numeric field is finite and bounded: one line naming the file and the key."""
    path = write_scenario("bad", default_with(section, key, value))
    with pytest.raises(ConfigError) as exc:
        load_config("bad")
    message = str(exc.value)
    assert str(path) in message and "\n" not in message
    full = key if section == "" else f"{section}.{key}"
    if section == "scoring.windows":  # named by index (type errors) or by the window's name
        assert "scoring.windows[" in message and key in message, message
    else:
        assert full in message, message


def child(section: str, body: str) -> str:
    """A scenario extending default that sets `body` in [section] ('' for the top level)."""
    return 'extends = "default"\n' + (f"[{section}]\n" if section else "") + body + "\n"


BAD_SCENARIOS = [
    # (id, scenario text, key the message must name, further fragments it must hold)
    ("impact-1e7", child("trajectory", "impact_time_s = 1e7"), "trajectory.impact_time_s",
     ("694.838", "3678.949", "radial free fall", "half period")),
    ("impact-below-free-fall", child("trajectory", "impact_time_s = 600.0"),
     "trajectory.impact_time_s", ("694.838",)),
    ("impact-nan", child("trajectory", "impact_time_s = nan"), "trajectory.impact_time_s",
     ("finite",)),
    ("sigma-range-inf", child("detection", "sigma_range_m = inf"), "detection.sigma_range_m",
     ("finite",)),
    ("sigma-bearing-nan", child("detection", "sigma_bearing = nan"), "detection.sigma_bearing",
     ("finite",)),
    ("sigma-bearing-absurd", child("detection", "sigma_bearing = 5.0"), "detection.sigma_bearing",
     ("[1e-12, 1]",)),
    ("fov-nan", child("detection", "fov_deg = nan"), "detection.fov_deg", ()),
    ("visibility-a-inf", child("detection", "visibility_a = inf"), "detection.visibility_a", ()),
    ("visibility-b-negative", child("detection", "visibility_b_per_km = -0.01"),
     "detection.visibility_b_per_km", ()),
    ("extends-dotdot", 'extends = "../x"\n', "extends", ("no path",)),
    ("extends-absolute", 'extends = "/etc/passwd"\n', "extends", ()),
    ("extends-subdir", 'extends = "sub/default"\n', "extends", ()),
    ("extends-not-a-string", "extends = 3\n", "extends", ()),
    ("periapsis-above-apoapsis", child("trajectory", "periapsis_radius_km = 3000.0"),
     "trajectory.periapsis_radius_km", ("apoapsis radius (2037.4 km",)),
    ("periapsis-negative", child("trajectory", "periapsis_radius_km = -5.0"),
     "trajectory.periapsis_radius_km", ()),
    ("periapsis-above-surface", child("trajectory", "periapsis_radius_km = 1800.0"),
     "trajectory.periapsis_radius_km", ("never reaches the surface",)),
    ("frame-rate-1e9", child("trajectory", "frame_rate_hz = 1e9"), "trajectory.frame_rate_hz",
     ("3e+12 frames", f"{MAX_FRAMES:,}", "GB")),
    ("frame-rate-inf", child("trajectory", "frame_rate_hz = inf"), "trajectory.frame_rate_hz", ()),
    ("start-after-impact", child("trajectory", "start_s = 3500.0"), "trajectory.start_s",
     ("impact at 3000",)),
    ("end-before-start", child("trajectory", "start_s = 100.0\nend_s = 50.0"),
     "trajectory.end_s", ()),
    ("jitter-knots", child("trajectory", "jitter_rate_sigma_rad_s = 1e-6\njitter_knot_s = 1e-4"),
     "trajectory.jitter_knot_s", ("jitter knots",)),
    ("thrust-nan", child("trajectory", "specific_force_body_m_s2 = [0.0, 0.0, nan]"),
     "trajectory.specific_force_body_m_s2[2]", ()),
    ("apoapsis-too-far", child("trajectory", "apoapsis_alt_km = 40000.0"),
     "trajectory.apoapsis_alt_km", ("radial free fall",)),
    ("window-after-impact",
     child("scoring", 'table_window = "late"\n[[scoring.windows]]\nname = "late"\n'
                      "start_s = 3100.0\nend_s = 3200.0"),
     "scoring.windows[late].start_s", ("impact at 3000",)),
    ("final-window-longer-than-descent", child("scoring", "final_window_s = 4000.0"),
     "scoring.final_window_s", ()),
    ("too-many-synthetic-craters", child("catalogue", "synthetic_min_diam_km = 0.05"),
     "catalogue.synthetic_min_diam_km", ("synthetic craters", "GB")),
    ("empty-synthetic-catalogue",
     child("catalogue", "synthetic_min_diam_km = 3000.0\nsynthetic_max_diam_km = 3400.0"),
     "catalogue.synthetic_min_diam_km", ("empty",)),
    ("healpix-order-13", child("catalogue", "healpix_order = 13"), "catalogue.healpix_order", ()),
    ("sweep-workers-0", child("sweep", "workers = 0"), "sweep.workers", ()),
    ("sweep-too-many-runs", child("sweep", f"seeds = {list(range(2000))}"), "sweep.seeds",
     ("12,000 runs",)),
    ("sweep-no-methods", child("sweep", "methods = []"), "sweep.methods", ()),
    ("max-condition-below-1", child("estimation", "max_condition = 0.5"),
     "estimation.max_condition", ()),
    ("consistency-probability-1", child("estimation", "consistency_probability = 1.0"),
     "estimation.consistency_probability", ()),
    ("assumed-sigma-none", child("estimation", 'assumed_sigma_bearing = "none"'),
     "estimation.assumed_sigma_bearing", ('"truth"',)),
    ("assumed-sigma-negative", child("estimation", "assumed_sigma_range_m = -1.0"),
     "estimation.assumed_sigma_range_m", ()),
    ("assumed-sigma-inf", child("estimation", "assumed_sigma_range_m = inf"),
     "estimation.assumed_sigma_range_m", ()),
    ("seed-negative", child("", "seed = -1"), "seed", ()),
]


@pytest.mark.parametrize(("text", "key", "fragments"), [c[1:] for c in BAD_SCENARIOS],
                         ids=[c[0] for c in BAD_SCENARIOS])
def test_bad_scenario_is_one_line_naming_file_and_key(workdir, text, key, fragments):
    path = write_scenario("bad", text)
    with pytest.raises(ConfigError) as exc:
        load_config("bad")
    message = str(exc.value)
    assert message.split(": ", 1)[0] == str(path.resolve()), message  # the file comes first
    assert f"{key} " in message or f"{key}:" in message, message
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


def test_impact_time_bounds_are_the_orbit_solvers_range(workdir):
    """The admissible interval is where orbit.periapsis_radius_for_impact solves: just inside
    loads, just outside is a ConfigError (not the solver's ValueError)."""
    lo, hi = impact_time_bounds_s(300.0)
    assert 694.8 < lo < 694.9 and 3678.9 < hi < 3679.0
    scoring = {"windows": [{"name": "w", "start_s": 0.0, "end_s": 600.0}], "table_window": "w",
               "final_window_s": 100.0}  # inside the shortest descent
    for t in (lo * (1 + 1e-6), hi * (1 - 1e-6)):
        cfg = load_config("default", overrides={"trajectory": {"impact_time_s": t},
                                                "scoring": scoring})
        assert cfg.trajectory.ballistic_impact_s() == t
    for t in (lo, hi, lo * (1 - 1e-6), hi * (1 + 1e-6)):
        with pytest.raises(ConfigError, match=r"trajectory\.impact_time_s"):
            load_config("default", overrides={"trajectory": {"impact_time_s": t}})


def test_given_periapsis_ignores_impact_time_and_thrust_lifts_the_surface_rule(workdir):
    cfg = load_config("default", overrides={"trajectory": {"periapsis_radius_km": 1650.0,
                                                           "impact_time_s": 1234.0}})
    assert cfg.trajectory.periapsis_radius_km == 1650.0
    # with thrust the orbit may still come down: only periapsis < apoapsis is required
    load_config("default", overrides={"trajectory": {"periapsis_radius_km": 1800.0,
                                                     "specific_force_body_m_s2": [0.0, 0.0, 1.0]}})


def test_jitter_horizon_follows_the_actual_descent(workdir):
    """The jitter's knots cover twice the ballistic descent (the given periapsis's when set, not
    the ignored impact_time_s), and its knot count is bounded on that span."""
    cfg = load_config("default").trajectory
    assert cfg.jitter_horizon_s() == 6000.0
    given = load_config("default", overrides={"trajectory": {
        "periapsis_radius_km": 1650.0, "impact_time_s": 80_000.0,
        "jitter_rate_sigma_rad_s": 1e-6, "jitter_knot_s": 0.01}}).trajectory
    assert 5060.0 < given.jitter_horizon_s() < 5070.0  # 2 x 2,532 s
    with pytest.raises(ConfigError, match=r"trajectory\.jitter_knot_s .*jitter knots"):
        load_config("default", overrides={"trajectory": {"jitter_rate_sigma_rad_s": 1e-6,
                                                         "jitter_knot_s": 0.005}})


def test_frame_limit_is_the_frame_count_not_the_rate(workdir):
    """10 Hz over the whole descent (30,001 frames) and 1 kHz over 100 s load; the estimate
    matches the frames of [start_s, min(end_s, impact)]."""
    cfg = load_config("default", overrides={"trajectory": {"frame_rate_hz": 10.0}})
    assert cfg.trajectory.frame_count_estimate() == 30_001
    cfg = load_config("default", overrides={"trajectory": {"frame_rate_hz": 1000.0,
                                                           "start_s": 100.0, "end_s": 200.0}})
    assert cfg.trajectory.frame_count_estimate() == 100_001
    with pytest.raises(ConfigError, match=r"trajectory\.frame_rate_hz"):
        load_config("default", overrides={"trajectory": {"frame_rate_hz": 1000.0}})


def test_shipped_scenarios_all_load(workdir):
    for path in sorted(Path("runs/scenarios").glob("*.toml")):
        cfg = load_config(path.stem)
        assert cfg.name == path.stem


# --- run ids --------------------------------------------------------------------------------------


@pytest.mark.parametrize("run_id", ["..", ".", "", "a/b", "../x", "/tmp/x", "x" * 101, "a b",
                                   "é", "-rf", ".hidden", "a\\b", "scenarios", "a\nb"])
def test_bad_run_ids_are_refused_in_one_line(workdir, run_id):
    with pytest.raises(ConfigError, match="run_id") as exc:
        validate_run_id(run_id)
    assert "\n" not in str(exc.value).replace(repr(run_id), "")
    with pytest.raises(ConfigError, match="run_id"):
        load_config("default", run_id=run_id)


@pytest.mark.parametrize("run_id", ["default", "run-1.2_x", "x" * 100, "A", "0"])
def test_good_run_ids_pass_unchanged(workdir, run_id):
    assert validate_run_id(run_id) == run_id
    assert load_config("default", run_id=run_id).run_id == run_id


def test_a_scenario_name_that_is_no_run_id_needs_an_explicit_one(workdir):
    path = workdir / "my scenario.toml"
    path.write_text('extends = "default"\n')
    with pytest.raises(ConfigError, match="--run-id"):
        load_config(str(path))
    assert load_config(str(path), run_id="mine").name == "my scenario"


# --- paths: the workspace, not the working directory ----------------------------------------------


def test_bare_names_come_from_the_workspace_whatever_the_cwd(workdir, monkeypatch,
                                                             tmp_path_factory):
    assert workspace().scenarios_dir == workdir / "runs" / "scenarios"
    assert scenario_path("default") == workdir / "runs" / "scenarios" / "default.toml"
    write_scenario("local", 'extends = "short"\nseed = 4\n')
    elsewhere = tmp_path_factory.mktemp("elsewhere")
    (elsewhere / "runs" / "scenarios").mkdir(parents=True)
    (elsewhere / "runs" / "scenarios" / "local.toml").write_text('extends = "default"\nseed = 9\n')
    monkeypatch.chdir(elsewhere)  # a cwd with its own runs/scenarios: ignored
    cfg = load_config("local")
    assert (cfg.seed, cfg.trajectory.start_s) == (4, 1800.0)
    assert cfg.catalogue.db_path == "catalogue/craters.duckdb"  # stays a (relative) string
    (workdir / "sub").mkdir()
    monkeypatch.chdir(workdir / "sub")
    assert load_config("local").seed == 4
    with pytest.raises(ConfigError, match=r"runs/scenarios/absent\.toml.*not found"):
        load_config("absent")


def test_a_toml_path_is_taken_as_given_and_its_parent_from_the_workspace(workdir, monkeypatch):
    mine = workdir / "mine"
    mine.mkdir()
    (mine / "exp.toml").write_text('extends = "short"\nseed = 6\n')
    (mine / "short.toml").write_text('extends = "default"\nseed = 99\n')  # not the parent
    monkeypatch.chdir(mine)
    cfg = load_config("exp.toml")
    assert (cfg.name, cfg.seed, cfg.trajectory.start_s) == ("exp", 6, 1800.0)
    monkeypatch.chdir(workdir)
    assert load_config("mine/exp.toml").seed == 6
    with pytest.raises(ConfigError, match=r"mine/nope\.toml: scenario not found"):
        load_config("mine/nope.toml")


@pytest.mark.parametrize("name", ["../default", "sub/default", "..", "/etc/passwd"])
def test_a_bare_scenario_name_with_a_path_is_refused(workdir, name):
    with pytest.raises(ConfigError, match="scenario"):
        load_config(name)


# --- truth apart from the navigator's assumptions -------------------------------------------------


def test_navigator_assumes_the_truth_by_default(workdir):
    cfg = load_config("default")
    assert (cfg.detection.sigma_bearing, cfg.detection.sigma_range_m) == (1e-4, 10.0)
    assert cfg.estimation.assumed_sigma_bearing is None
    assert cfg.estimation.assumed_sigma_range_m is None
    assert cfg.navigator_sigmas() == (1e-4, 10.0)
    assert cfg.estimation.consistency_probability == 1 - 1e-6
    assert cfg.estimation.max_condition == 1e10
    shown = json.loads(json.dumps(to_dict(cfg)))["estimation"]  # as config.json shows it
    assert (shown["assumed_sigma_bearing"], shown["assumed_sigma_range_m"]) == ("truth", "truth")
    # a changed truth is followed by a navigator that assumes the truth
    changed = load_config("default", overrides={"detection": {"sigma_range_m": 3.0}})
    assert changed.navigator_sigmas() == (1e-4, 3.0)


def test_a_mistuned_navigator_can_be_written_down(workdir):
    write_scenario("mistuned", 'extends = "default"\n[estimation]\nassumed_sigma_bearing = 5e-4\n'
                   'assumed_sigma_range_m = "Truth"\n')
    base, cfg = load_config("default"), load_config("mistuned")
    assert cfg.detection == base.detection  # the truth (and the detect stage's key) unchanged
    assert config_hash(cfg.detection) == config_hash(base.detection)
    assert config_hash(cfg.estimation) != config_hash(base.estimation)
    assert cfg.navigator_sigmas() == (5e-4, 10.0)
    shown = to_dict(cfg)["estimation"]
    assert (shown["assumed_sigma_bearing"], shown["assumed_sigma_range_m"]) == (5e-4, "truth")
    # an explicit number equal to the truth is a different intent, and hashes apart from "truth"
    same = load_config("default", overrides={"estimation": {"assumed_sigma_range_m": 10.0}})
    assert same.navigator_sigmas() == base.navigator_sigmas()
    assert config_hash(same.estimation) != config_hash(base.estimation)


def test_default_toml_comments_every_key(workdir):
    """Every `key = value` line of default.toml carries a comment (unit and meaning), except the
    scoring windows' own rows, which a comment above them describes."""
    in_window, bare = False, []
    for line in Path("runs/scenarios/default.toml").read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("["):
            in_window = stripped == "[[scoring.windows]]"
        elif "=" in stripped and not stripped.startswith("#") and not in_window:
            if "#" not in stripped:
                bare.append(stripped)
    assert bare == []


def test_pixels_need_a_rendered_frame_of_the_trajectory(workdir):
    """detection.source = "pixels" over a render window that holds no trajectory frame would
    see nothing: a one-line error naming render.start_s."""
    path = write_scenario("pix", 'extends = "images"\n[trajectory]\nstart_s = 1200.0\n'
                          'end_s = 1220.0\n[render]\nstart_s = 1300.0\nend_s = 1310.0\n')
    with pytest.raises(ConfigError, match=r"render\.start_s: no trajectory frame") as exc:
        load_config("pix")
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    write_scenario("pix2", 'extends = "images"\n[trajectory]\nstart_s = 1200.0\n'
                   'end_s = 1220.0\n[render]\nstart_s = 1210.0\nend_s = 1210.0\n')
    assert load_config("pix2").render.start_s == 1210.0


def test_tracking_alone_needs_a_filter_from_the_start(workdir):
    """identification.mode = "tracking" cannot start from a first fix it never makes."""
    write_scenario("trk", 'extends = "lost"\n[identification]\nmode = "tracking"\n')
    with pytest.raises(ConfigError, match=r"identification\.mode.*tracking_lis"):
        load_config("trk")


def test_false_detections_need_identification_by_algorithm(workdir):
    write_scenario("fd", 'extends = "camera"\n[detection]\nfalse_detection_share = 0.2\n')
    with pytest.raises(ConfigError, match=r"detection\.false_detection_share"):
        load_config("fd")


def test_a_navigator_that_assumes_another_camera_mounting(workdir):
    """The misalignment rotates true body bearings into the navigator's body frame: the
    rotation between the true and the assumed mounting; none for a perfect calibration, and
    refused where it cannot apply (the paper's camera, identification by algorithm)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    write_scenario("mis", 'extends = "camera"\n[detection]\ncamera_mounting_deg = [0.1, 0.0, '
                   '0.05]\n[estimation]\nassumed_camera_mounting_deg = [0.0, 0.0, 0.0]\n')
    m = load_config("mis").navigator_misalignment()
    body_from_cam = Rotation.from_euler("ZYX", np.radians([0.1, 0.0, 0.05])).as_matrix()
    np.testing.assert_allclose(m, body_from_cam.T, atol=1e-15)  # assumed: the identity
    assert load_config("camera").navigator_misalignment() is None
    write_scenario("mis_paper", 'extends = "default"\n[estimation]\n'
                   'assumed_camera_mounting_deg = [0.0, 0.0, 0.0]\n')
    with pytest.raises(ConfigError, match=r'assumed_camera_mounting_deg.*sensor = "physical"'):
        load_config("mis_paper")
    write_scenario("mis_id", 'extends = "identify"\n[estimation]\n'
                   'assumed_camera_mounting_deg = [0.0, 0.0, 0.0]\n')
    with pytest.raises(ConfigError, match=r'assumed_camera_mounting_deg.*mode = "simulated"'):
        load_config("mis_id")
    write_scenario("mis_bad", 'extends = "camera"\n[estimation]\n'
                   'assumed_camera_mounting_deg = [0.0, 0.0]\n')
    with pytest.raises(ConfigError, match=r"assumed_camera_mounting_deg"):
        load_config("mis_bad")


def test_render_detector_and_crater_ages_are_checked(workdir):
    """render.detector names a known detector, terrain.crater_age_max is a normalised age in
    [0, 1]; one line naming the key; images-learned picks the learned one."""
    path = write_scenario("det", 'extends = "images"\n[render]\ndetector = "yolo"\n')
    with pytest.raises(ConfigError, match=r"render\.detector = 'yolo': must be one of") as exc:
        load_config("det")
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    write_scenario("age", 'extends = "images"\n[terrain]\ncrater_age_max = 2.0\n')
    with pytest.raises(ConfigError, match=r"terrain\.crater_age_max"):
        load_config("age")
    assert load_config("images-learned").render.detector == "learned"
    assert load_config("images").render.detector == "classical"
    assert load_config("images").terrain.crater_age_max == 0.0
