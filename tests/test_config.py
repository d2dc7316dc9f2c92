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

from pipeline.config import ConfigError, RunConfig, config_hash, load_config, to_dict


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
            current = stripped.strip("[]")
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
], ids=lambda v: v if isinstance(v, str) and "." in v else None)
def test_out_of_range_names_the_key(workdir, section, key, value, full_key):
    write_scenario("bad", default_with(section, key, value))
    with pytest.raises(ConfigError, match=full_key.replace(".", r"\.")):
        load_config("bad")


def test_negative_generator_seed_is_a_config_error(workdir):
    write_scenario("bad", default_with("catalogue", "seed", "-1"))
    with pytest.raises(ConfigError, match=r"catalogue\.seed"):
        load_config("bad")


def test_run_id_argument_is_not_overridden_by_the_file(workdir):
    write_scenario("rid", 'extends = "default"\nrun_id = "elsewhere"\nname = "other"\n')
    try:
        cfg = load_config("rid", run_id="mine")
    except ConfigError:
        return  # rejecting run_id/name as unknown scenario keys is a fix too
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
